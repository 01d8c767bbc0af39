"""The package versions a flight or a training run was computed with.

A seeded evaluation repeats trial for trial on one machine with one set of packages. Across package versions it need
not: numpy, numba/llvmlite, scipy, MuJoCo or the QP solvers may round one operation differently, and a flight near
the edge of a collision or of the time limit then ends the other way (how often: docs/evaluation.md, "Reproducing a
table"). So every ``eval.py`` manifest and every checkpoint records these versions, a resumed evaluation names the
ones that changed, and ``python -m shield_nav.tools.paired`` says when its two sides were flown with different ones. The
processor's SIMD extensions (:func:`cpu_simd`) are recorded and compared beside them: with the same packages, two
machines flew a few trials differently (2026-12-01, docs/evaluation.md); numba compiles for the processor and numpy,
MuJoCo and torch choose kernels by it.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform

__all__ = [
    "BLAS_CORE",
    "PACKAGES",
    "SIMD_FLAGS",
    "cpu_model",
    "cpu_simd",
    "format_differences",
    "manifest_record",
    "package_versions",
    "numpy_simd_targets",
    "pinned_arithmetic_environment",
    "version_differences",
]

#: The distributions whose arithmetic a flight or a training step goes through (their PyPI names).
PACKAGES = (
    "numpy",
    "numba",
    "llvmlite",
    "scipy",
    "torch",
    "mujoco",
    "qpsolvers",
    "osqp",
    "daqp",
    "quadprog",
    "onnxruntime",
    "rsl-rl-lib",
    "gymnasium",
)


def package_versions(packages: tuple[str, ...] = PACKAGES) -> dict[str, str | None]:
    """``{"python": ..., name: installed version or None}`` for ``packages``."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in packages:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo`` on Linux; ``platform.processor()`` elsewhere, maybe empty).

    numpy and MuJoCo pick SIMD kernels by processor, so it belongs with the package versions.
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


#: The ``/proc/cpuinfo`` flags of the SIMD extensions numeric libraries choose kernels by, in the order recorded.
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_vnni",
              "avx512_bf16", "amx_tile", "asimd", "sve")  # fmt: skip


def cpu_simd() -> str | None:
    """The :data:`SIMD_FLAGS` the first processor of ``/proc/cpuinfo`` reports, space-separated in that order.

    ``""`` where it reports none of them; None where there is no ``/proc/cpuinfo`` flags line (not Linux). The
    model name does not tell these apart (two machines both named "AMD EPYC" differed, 2026-12-01).
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    have = set(line.split(":", 1)[1].split())
                    return " ".join(flag for flag in SIMD_FLAGS if flag in have)
    except OSError:
        pass
    return None


BLAS_CORE = "Prescott"
"""The OpenBLAS kernel set a fixed-order evaluation pins on x86-64 (``OPENBLAS_CORETYPE``): the SSE3 kernels every
x86-64 processor runs. numpy calls OpenBLAS for its small matrix products (the vehicle's mixer and motor torques, the
shield's products), and OpenBLAS otherwise picks its kernels by processor, whose results differ in the last bits
(docs/evaluation.md, "A flight that does not depend on the processor")."""


def numpy_simd_targets() -> list[str]:
    """The run-time dispatch targets numpy uses on this processor (e.g. ``['X86_V3', 'X86_V4', ...]``).

    numpy compiles some loops (float64 ``sin``, ``cos``, ``exp``, ... among them) once per target above its baseline
    and picks the best one the processor has when it loads; its AVX-512 loops round differently from its baseline
    ones. ``NPY_DISABLE_CPU_FEATURES`` switches targets off at load; a switched-off target is not listed here.
    """
    try:  # numpy >= 2
        from numpy._core import _multiarray_umath as umath
    except ImportError:  # numpy 1.26, which pyproject.toml allows
        from numpy.core import _multiarray_umath as umath  # type: ignore[no-redef]
    return [t for t in umath.__cpu_dispatch__ if umath.__cpu_features__.get(t)]


def pinned_arithmetic_environment(environ: dict | None = None, machine: str | None = None,
                                  numpy_targets: list[str] | None = None) -> dict | None:  # fmt: skip
    """The environment to re-run with so that the flights do not depend on the x86-64 processor, or None.

    OpenBLAS is pinned to :data:`BLAS_CORE` and numpy's dispatch targets in use (``numpy_targets``, by default
    :func:`numpy_simd_targets`) are switched off with ``NPY_DISABLE_CPU_FEATURES``, so numpy runs the loops of its
    baseline build on every processor. None when both already hold, or off x86-64 (other architectures have other
    kernel names; the project makes no cross-architecture claim). Both libraries read these variables when they load,
    so a process that has imported numpy must be started again with them (``eval.py`` does, for ``network:
    fixed_order``).
    """
    env = dict(os.environ if environ is None else environ)
    arch = (machine if machine is not None else platform.machine()).lower()
    targets = numpy_simd_targets() if numpy_targets is None else list(numpy_targets)
    if arch not in ("x86_64", "amd64") or (env.get("OPENBLAS_CORETYPE") == BLAS_CORE and not targets):
        return None
    env["OPENBLAS_CORETYPE"] = BLAS_CORE
    if targets:
        already = env.get("NPY_DISABLE_CPU_FEATURES", "").replace(",", " ").split()
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(dict.fromkeys([*already, *targets]))
    return env


def manifest_record(manifest: dict) -> dict | None:
    """What an ``eval.py`` manifest records of its arithmetic: its ``packages`` plus ``cpu_simd`` where recorded.

    None for a manifest written before package versions were recorded; a manifest written before ``cpu_simd`` was
    recorded gives its packages alone, so :func:`version_differences` does not report the unknown as different.
    """
    packages = manifest.get("packages")
    if not isinstance(packages, dict):
        return None
    return {**packages, **({"cpu_simd": manifest["cpu_simd"]} if "cpu_simd" in manifest else {})}


def version_differences(a: dict | None, b: dict | None) -> dict[str, list]:
    """``{name: [a's version, b's version]}`` for every name both records hold with different versions.

    A missing record (an output written before versions were recorded) compares as no difference: unknown is not
    reported as different.
    """
    if not isinstance(a, dict) or not isinstance(b, dict):
        return {}
    return {k: [a[k], b[k]] for k in sorted(set(a) & set(b)) if a[k] != b[k]}


def format_differences(diff: dict[str, list]) -> str:
    """``numpy 2.4.6 / 2.5.2, scipy 1.17.1 / 1.18.1`` (empty when there is none)."""
    return ", ".join(f"{k} {x} / {y}" for k, (x, y) in diff.items())
