"""Atomic JSON files: the markers and results that resume and selection trust.

A training pipeline's stage markers, an evaluation's per-unit results and every summary are read back later to
decide what to skip. Each is written to a temporary file beside its target and renamed over it, so a kill at any
moment leaves either the old file or the new one, never half of one. numpy scalars and arrays are written as plain
numbers and lists; any other type that json cannot write raises ``TypeError`` naming it, and leaves the target as it
was.
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

__all__ = ["json_default", "write_json"]


def write_json(path: str, data: Any, indent: int = 1) -> None:
    """Write ``data`` to ``path`` as JSON, atomically (temporary file + rename); numpy values become plain ones."""
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=indent, default=json_default)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def json_default(o: Any) -> Any:
    """``json.dump``'s ``default``: numpy scalars and arrays as plain values, anything else a ``TypeError``."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")
