"""What did the crashed flights hit? Collision breakdown of an evaluation output by obstacle class.

``python -m shield_nav.collisions eval_out/ablation [--rows a,b] [--speeds 3,5] [--json]``

reads the per-unit trial files of an ``eval.py`` output folder, takes the last recorded position of every trial
that ended in a collision, regenerates the unit's scene (scenes are pure functions of family, index and seed) and
names the nearest surface: a primitive's kind, ``thin`` when its radius is below :data:`THIN_RADIUS`, and the axis
orientation of cylinders and capsules (``vertical`` within 18 deg of z, ``horizontal`` within 12 deg of the xy
plane, ``inclined`` otherwise), or the floor or ceiling of the flight volume. Nearest surfaces farther than
:data:`MAX_HIT_DISTANCE` are ``unresolved`` (moving obstacles, which are not regenerated here). It tells apart
failures of perception on obstacle kinds the training scenes never had from failures on familiar ones.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
from collections import Counter, defaultdict

import numpy as np

from envs.scenes import Primitive, Scene, make_scene
from envs.scenes.sdf import primitive_sdf

THIN_RADIUS = 0.08
"""Cylinders and capsules with a smaller radius (m) are ``thin`` (poles, frame bars)."""
MAX_HIT_DISTANCE = 0.6
"""A nearest surface farther than this (m) from the final position is ``unresolved``."""


def primitive_class(prim: Primitive) -> str:
    """Class name of one primitive: ``box``, ``sphere``, or ``<kind>[ thin] <vertical|horizontal|inclined>``."""
    if prim.kind in ("cylinder", "capsule"):
        axis = np.subtract(prim.p1, prim.p0)
        up = abs(axis[2]) / max(float(np.linalg.norm(axis)), 1e-12)
        orient = "vertical" if up > 0.95 else "horizontal" if up < 0.2 else "inclined"
        return f"{prim.kind}{' thin' if prim.radius < THIN_RADIUS else ''} {orient}"
    return prim.kind


def classify_hit(scene: Scene, pos: np.ndarray) -> tuple[str, float]:
    """The class of the surface nearest to ``pos`` (3,) in ``scene`` and its signed distance (m)."""
    p = np.asarray(pos, dtype=np.float64).reshape(1, 3)
    if not np.isfinite(p).all():
        raise ValueError(f"position must be finite, got {pos!r}")
    best, dist = "unresolved", np.inf
    if scene.floor:
        best, dist = "floor", float(p[0, 2] - scene.bounds_lo[2])
    if scene.ceiling and scene.bounds_hi[2] - p[0, 2] < dist:
        best, dist = "ceiling", float(scene.bounds_hi[2] - p[0, 2])
    for prim in scene.primitives:
        d = float(primitive_sdf(prim, p)[0])
        if d < dist:
            best, dist = primitive_class(prim), d
    return (best if dist <= MAX_HIT_DISTANCE else "unresolved"), dist


def breakdown(
    out_dir: str, rows: list[str] | None = None, speeds: list[float] | None = None
) -> dict[tuple[str, float], Counter]:
    """(row, speed) -> Counter of hit classes over the collided trials of an eval output folder."""
    files = sorted(glob.glob(os.path.join(out_dir, "units", "*.json")))
    if not files:
        raise FileNotFoundError(f"no unit files under {os.path.join(out_dir, 'units')!r}: not an eval.py output")
    out: dict[tuple[str, float], Counter] = defaultdict(Counter)
    for path in files:
        with open(path) as fh:
            unit = json.load(fh)
        if (rows and unit["row"] not in rows) or (speeds and float(unit["speed"]) not in speeds):
            continue
        hits = [t for t in unit["trials"] if t["outcome"] == "collision"]
        key = (unit["row"], float(unit["speed"]))
        out[key].update()  # rows without collisions still appear
        if not hits:
            continue
        scene = make_scene(unit["family"], int(unit["scene"]))  # eval.py flies the family's default seed
        for t in hits:
            if not t.get("traj"):
                raise ValueError(f"{path}: trial {t.get('trial')} has no trajectory (trajectory_every too large?)")
            out[key][classify_hit(scene, np.asarray(t["traj"][-1][:3]))[0]] += 1
    return dict(out)


def format_table(result: dict[tuple[str, float], Counter]) -> str:
    """Markdown table: one line per (row, speed), the share of collisions per class (%), n collisions."""
    classes = sorted({c for cnt in result.values() for c in cnt}, key=lambda c: -sum(r[c] for r in result.values()))
    lines = ["| row | speed | n | " + " | ".join(classes) + " |", "|---|---:|---:|" + "---:|" * len(classes)]
    for (row, speed), cnt in sorted(result.items()):
        n = sum(cnt.values())
        cells = [f"{100.0 * cnt[c] / n:.0f}" if n else "-" for c in classes]
        lines.append(f"| {row} | {speed:g} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """CLI entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", help="an eval.py output folder (eval_out/<name>)")
    ap.add_argument("--rows", default="", help="comma-separated rows (default: all)")
    ap.add_argument("--speeds", default="", help="comma-separated target speeds (default: all)")
    ap.add_argument("--json", action="store_true", help="print one JSON line instead of the table")
    a = ap.parse_args(argv)
    rows = [r for r in a.rows.split(",") if r] or None
    try:
        speeds = [float(s) for s in a.speeds.split(",") if s] or None
    except ValueError:
        ap.error(f"--speeds must be numbers, got {a.speeds!r}")
    result = breakdown(a.out_dir, rows, speeds)
    if a.json:
        print(
            json.dumps([{"row": r, "speed": s, "n": sum(c.values()), "hits": dict(c)} for (r, s), c in result.items()])
        )
    else:
        print(format_table(result))


if __name__ == "__main__":
    main()
