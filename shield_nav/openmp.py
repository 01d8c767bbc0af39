"""How long idle OpenMP threads busy-wait, set before torch or numba load their OpenMP runtime (libgomp).

torch's CPU kernels and numba's parallel loops (the depth renderer, the expert's tracer) run on libgomp thread pools.
After each parallel region libgomp's idle threads spin for the next one, 300,000 times by default, before they sleep.
Where another process wants the same cores (a training run beside an evaluation on a 2-core machine), those spins
take the cores from the threads that have work, and both processes slow down several-fold. ``train.py``, ``eval.py``,
``python -m shield_nav.bench`` and the analysis tools run with ``-m`` (imitation, route_view, speed_budget)
therefore shorten the spin to :data:`SPINCOUNT` before anything loads libgomp, unless the user chose
``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` themselves (``GOMP_SPINCOUNT=300000`` restores libgomp's default).
Measured in docs/training.md, "Threads".

Nothing here imports torch or numba; the variable only acts if it is set before they load.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

__all__ = ["SPINCOUNT", "limit_spinning"]

SPINCOUNT = "10000"
"""libgomp's busy-wait count for idle threads, set by :func:`limit_spinning`."""


def limit_spinning(environ: MutableMapping[str, str] | None = None) -> bool:
    """Set ``GOMP_SPINCOUNT`` to :data:`SPINCOUNT` unless ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` is set.

    Args:
        environ: The environment to edit (default: ``os.environ``).

    Returns:
        Whether it set the variable (False where the user's choice stands).
    """
    env = os.environ if environ is None else environ
    if "OMP_WAIT_POLICY" in env or "GOMP_SPINCOUNT" in env:
        return False
    env["GOMP_SPINCOUNT"] = SPINCOUNT
    return True
