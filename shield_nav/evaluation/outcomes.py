"""Every trial's outcome in one small file, so a finished run can be paired trial by trial without its unit files.

``eval.py`` writes ``outcomes.csv.gz`` beside ``summary.json``: one line per trial with the keys that pin it
(``row, family, scene, speed, trial`` and its ``seed``, which paired checks), how it ended (``outcome``,
``steps``) and ``flew_over`` (a success over the obstacles' tops; empty where not recorded). About 30 kB for a full
Table I row set, where the unit files hold tens of MB of trajectories, so it can be kept in ``docs/data/`` with the
summary; ``python -m shield_nav.tools.paired`` reads it where a folder has no unit files. Written with a zero gzip time
stamp, so the same trials give the same bytes.
"""

from __future__ import annotations

import csv
import gzip
import io
import os

__all__ = ["FIELDS", "OUTCOMES_FILE", "read_outcomes", "write_outcomes"]

OUTCOMES_FILE = "outcomes.csv.gz"
FIELDS = ("row", "family", "scene", "speed", "trial", "seed", "outcome", "steps", "flew_over")


def write_outcomes(out_dir: str, unit_results: list[dict]) -> str:
    """Write the trials of ``unit_results`` (unit files' contents) to ``out_dir/outcomes.csv.gz``; return its path."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(FIELDS)
    for u in unit_results:
        for t in u["trials"]:
            over = (t.get("metrics") or {}).get("flew_over")
            w.writerow([u["row"], u["family"], int(u["scene"]), float(u["speed"]), int(t["trial"]), int(t["seed"]),
                        t["outcome"], int(t["steps"]), "" if over is None else float(over)])  # fmt: skip
    path = os.path.join(out_dir, OUTCOMES_FILE)
    tmp = path + ".tmp"
    with open(tmp, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz:
        gz.write(buf.getvalue().encode())
    os.replace(tmp, path)
    return path


def read_outcomes(path: str) -> list[dict]:
    """The trials of an ``outcomes.csv.gz``, one record each.

    Keys ``row, family, scene, speed, trial, seed, outcome, steps`` and ``metrics`` (``{"flew_over": x}``, empty
    where it was not recorded): the shape of a unit file's trial that :mod:`shield_nav.tools.paired` reads.
    """
    with gzip.open(path, "rt", newline="") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != FIELDS:
            raise ValueError(f"{path!r}: columns {reader.fieldnames}, expected {list(FIELDS)}")
        out = []
        for r in reader:
            out.append({
                "row": r["row"], "family": r["family"], "scene": int(r["scene"]), "speed": float(r["speed"]),
                "trial": int(r["trial"]), "seed": int(r["seed"]), "outcome": r["outcome"], "steps": int(r["steps"]),
                "metrics": {} if r["flew_over"] == "" else {"flew_over": float(r["flew_over"])},
            })  # fmt: skip
    return out
