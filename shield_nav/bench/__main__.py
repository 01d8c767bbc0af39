"""Benchmarks: ``python -m shield_nav.bench <name> [--json] [options]``.

Each benchmark is a module ``shield_nav.bench.<name>`` with ``main(argv: list[str]) -> dict``. It prints
human-readable progress and, with ``--json``, the final line printed is one JSON object (the contract in
DESIGN.md). Timing lives here, never in tests.
"""

from __future__ import annotations

import importlib
import sys

from shield_nav.openmp import limit_spinning

limit_spinning()  # as train.py and eval.py do, so a timing measures what they run (shield_nav/openmp.py)

BENCHMARKS = (
    "vehicle",
    "fields",
    "depth",
    "env",
    "train",
    "shield",
    "expert",
    "startup",
    "network",
    "deploy",
    "flights",
)


def main(argv: list[str] | None = None) -> int:
    """Dispatch to ``shield_nav.bench.<name>.main``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        print("available:", ", ".join(BENCHMARKS))
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in BENCHMARKS:
        print(f"unknown benchmark {name!r}; available: {', '.join(BENCHMARKS)}", file=sys.stderr)
        return 2
    try:
        module = importlib.import_module(f"shield_nav.bench.{name}")
    except ModuleNotFoundError as err:
        if err.name == f"shield_nav.bench.{name}":
            print(f"benchmark {name!r} is not implemented yet", file=sys.stderr)
            return 2
        raise
    module.main(rest)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
