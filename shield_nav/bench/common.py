"""Helpers shared by the benchmarks: argument parsing, machine facts, and the JSON last line."""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time
from collections.abc import Callable


def parser(name: str, description: str) -> argparse.ArgumentParser:
    """An ``argparse`` parser with the ``--json`` flag every benchmark takes."""
    p = argparse.ArgumentParser(prog=f"python -m shield_nav.bench {name}", description=description)
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    return p


def machine() -> dict:
    """Facts that make a timing comparable: the processor, CPU count, Python, platform, libgomp's spin count.

    The processor's model and SIMD extensions are there because machines of one name differ in them (2026-12-01);
    the spin count is shield_nav/openmp.py's.
    """
    from shield_nav.provenance import cpu_model, cpu_simd

    return {
        "cpu_model": cpu_model(),
        "cpu_simd": cpu_simd(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "gomp_spincount": os.environ.get("GOMP_SPINCOUNT"),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
    }


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def time_it(fn: Callable[[], object], min_time: float = 1.0, min_reps: int = 3) -> tuple[float, int]:
    """Call ``fn`` repeatedly for at least ``min_time`` seconds; return (seconds per call, calls)."""
    reps = 0
    t0 = time.perf_counter()
    while True:
        fn()
        reps += 1
        elapsed = time.perf_counter() - t0
        if reps >= min_reps and elapsed >= min_time:
            return elapsed / reps, reps


def emit(result: dict, as_json: bool) -> None:
    """Print the result: a readable block, and with ``as_json`` one JSON object as the very last line."""
    if as_json:
        print(json.dumps(result, sort_keys=False))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")
