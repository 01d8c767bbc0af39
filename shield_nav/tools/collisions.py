"""Collision and time-out breakdowns of an eval output: what did the crashes hit, how did the time-outs end?

``python -m shield_nav.tools.collisions eval_out/ablation [--rows a,b] [--speeds 3,5] [--json]``

reads the per-unit trial files of an ``eval.py`` output folder, takes the last recorded position of every trial
that ended in a collision, regenerates the unit's scene (scenes are pure functions of family, index and seed) and
names the nearest surface: a primitive's kind, ``thin`` when its radius is below :data:`THIN_RADIUS`, and the axis
orientation of cylinders and capsules (``vertical`` within 18 deg of z, ``horizontal`` within 12 deg of the xy
plane, ``inclined`` otherwise), or the floor or ceiling of the flight volume. Nearest surfaces farther than
:data:`MAX_HIT_DISTANCE` are ``unresolved`` (moving obstacles, which are not regenerated here). It tells apart
failures of perception on obstacle kinds the training scenes never had from failures on familiar ones.

``--bearing`` asks a second question: was the obstacle in front of the vehicle when it hit it? The **approach
bearing** is the horizontal angle between the direction of travel (the last two recorded trajectory points) and the
direction to the nearest surface point of the obstacle hit. Below half the camera's horizontal field of view
(``--hfov``, default the camera's 87 deg) the obstacle was inside the view cone around the direction of travel: a
failure to avoid what the camera showed. Above it, the vehicle clipped something beside it, which it could only
have avoided by remembering it. Floor and ceiling hits have no horizontal bearing and are left out. Outputs that
record the heading (a fifth trajectory column, the yaw of the camera's axis; written since 2026-11-28) add three
numbers from it: the share of crashes whose obstacle lay inside the camera's horizontal view (``in_camera``), the
share that happened while the vehicle moved more than half the field of view off its camera's axis (``blind``:
flying sideways or backwards into space the camera did not show), and the median yaw rate over the last half second
before the crash (``yaw_rate_deg_s``: turning hard, or flying straight). Outputs of a shielded row record, as a sixth
column, the share of the control steps since the previous point on which the shield acted (since 2026-11-28,
later); from it ``shield_share`` is the mean over the crashes of the share of their last half second's steps with the
shield acting.

``--timeouts`` asks about the flights that ran out of time instead: did each one stall (no metre of closing on the
goal in its last 5 s: circling or hovering in a pocket), or was it still on its way (too slow)? It reports, per row
and speed, the stalled count, when the stalled flights last closed in and how far they were left, and the closing
flights' distance left and closing speed (:func:`timeouts`; the stall rule is
:class:`shield_nav.safety.escape.StallEscape`'s), and how many of them circled (below).

``--circling`` asks of every flight, whatever its outcome, whether it flew in circles: whether its heading turned
through :data:`CIRCLE_TURNS` full turns or more, net, within some :data:`CIRCLE_WINDOW_S` of the flight
(:func:`max_turns`; outputs with the heading column). A flight that orbits a pocket turns its camera round and round
in one direction; one that threads clutter turns left and right, and its net rotation stays small. Per row and speed
it counts the circling flights by outcome (:func:`circling`).

``--sides`` asks of the successful flights where they went: the share of each one's recorded points within
``--margin`` (default :data:`SIDE_MARGIN`) of the flight volume's lateral sides, the y bounds that run along the
start-to-goal axis (:func:`sides`). A flight that threads a scene keeps off them; one that finds a way along the
scene's edge does not.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
from collections import Counter, defaultdict
from collections.abc import Iterator

import numpy as np

from envs.camera.config import CameraConfig
from envs.scenes import Primitive, Scene, make_scene
from envs.scenes.sdf import primitive_sdf
from envs.vehicle.config import VehicleConfig
from shield_nav.evaluation.metrics import CIRCLE_TURNS, CIRCLE_WINDOW_S, max_turns

THIN_RADIUS = 0.08
"""Cylinders and capsules with a smaller radius (m) are ``thin`` (poles, frame bars)."""
MAX_HIT_DISTANCE = 0.6
"""A nearest surface farther than this (m) from the final position is ``unresolved``."""
YAW_WINDOW_S = 0.5
"""The window [s] before a crash over which :func:`yaw_rate_before` averages the yaw rate."""
SIDE_MARGIN = 1.5
"""``--sides``: a point within this distance [m] of the flight volume's lateral sides is beside them."""
OUTCOMES = ("success", "collision", "timeout", "out_of_bounds")
"""A trial's outcomes, in the order :func:`format_circling` lists them."""


def primitive_class(prim: Primitive) -> str:
    """Class name of one primitive: ``box``, ``sphere``, or ``<kind>[ thin] <vertical|horizontal|inclined>``."""
    if prim.kind in ("cylinder", "capsule"):
        axis = np.subtract(prim.p1, prim.p0)
        up = abs(axis[2]) / max(float(np.linalg.norm(axis)), 1e-12)
        orient = "vertical" if up > 0.95 else "horizontal" if up < 0.2 else "inclined"
        return f"{prim.kind}{' thin' if prim.radius < THIN_RADIUS else ''} {orient}"
    return prim.kind


def _nearest(scene: Scene, pos: np.ndarray) -> tuple[str, float, Primitive | None]:
    """Class, signed distance and primitive (``None`` for the floor or ceiling) of the surface nearest to ``pos``."""
    p = np.asarray(pos, dtype=np.float64).reshape(1, 3)
    if not np.isfinite(p).all():
        raise ValueError(f"position must be finite, got {pos!r}")
    best, dist, prim_best = "unresolved", np.inf, None
    if scene.floor:
        best, dist = "floor", float(p[0, 2] - scene.bounds_lo[2])
    if scene.ceiling and scene.bounds_hi[2] - p[0, 2] < dist:
        best, dist = "ceiling", float(scene.bounds_hi[2] - p[0, 2])
    for prim in scene.primitives:
        d = float(primitive_sdf(prim, p)[0])
        if d < dist:
            best, dist, prim_best = primitive_class(prim), d, prim
    return best, dist, prim_best


def classify_hit(scene: Scene, pos: np.ndarray) -> tuple[str, float]:
    """The class of the surface nearest to ``pos`` (3,) in ``scene`` and its signed distance (m)."""
    best, dist, _ = _nearest(scene, pos)
    return (best if dist <= MAX_HIT_DISTANCE else "unresolved"), dist


def approach_bearing(scene: Scene, traj: np.ndarray) -> tuple[str, float | None]:
    """Hit class and approach bearing (deg, in [0, 180]) of a crashed trajectory ``(T, >=3)``, ``T >= 2``.

    The bearing is the horizontal angle between the last displacement ``traj[-1] - traj[-2]`` and the direction from
    the last position to the nearest surface point (minus the primitive's SDF gradient, by central differences).
    ``None`` for the floor, the ceiling, unresolved hits and a vehicle that did not move horizontally.
    """
    tr = np.asarray(traj, dtype=np.float64)
    if tr.ndim != 2 or tr.shape[0] < 2 or tr.shape[1] < 3:
        raise ValueError(f"need a trajectory of >= 2 points (T, >=3), got shape {tr.shape}")
    pos = tr[-1, :3]
    cls, dist, prim = _nearest(scene, pos)
    if prim is None or dist > MAX_HIT_DISTANCE:
        return (cls if dist <= MAX_HIT_DISTANCE else "unresolved"), None
    return cls, _angle_deg(tr[-1, :2] - tr[-2, :2], _toward_surface(prim, pos))


def _toward_surface(prim: Primitive, pos: np.ndarray) -> np.ndarray:
    """Horizontal direction (unnormalised) from ``pos`` to the primitive's nearest surface point.

    Minus the SDF's gradient, by central differences.
    """
    h = 1e-5
    return -np.array([primitive_sdf(prim, np.stack([pos + h * e, pos - h * e]))[[0, 1]] @ [1.0, -1.0] / (2 * h)
                      for e in np.eye(3)[:2]])  # fmt: skip


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float | None:
    """Angle between two horizontal vectors (deg, in [0, 180]); ``None`` if either is (nearly) zero."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-9 or nb < 1e-9:
        return None
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def camera_angles(scene: Scene, traj: np.ndarray) -> tuple[float | None, float | None]:
    """Angles (deg) from the camera's horizontal axis at the crash to the obstacle hit and to the direction of travel.

    ``traj`` is ``(T, 5)``: x, y, z, speed, heading [rad] (:func:`approach_bearing` for the rest). The first angle is
    ``None`` where the approach bearing is (floor, ceiling, unresolved); the second where the vehicle did not move.
    """
    tr = np.asarray(traj, dtype=np.float64)
    if tr.ndim != 2 or tr.shape[0] < 2 or tr.shape[1] < 5:
        raise ValueError(f"need a trajectory with a heading column (T >= 2, 5), got shape {tr.shape}")
    axis = np.array([np.cos(tr[-1, 4]), np.sin(tr[-1, 4])])
    pos = tr[-1, :3]
    _, dist, prim = _nearest(scene, pos)
    to_obstacle = None
    if prim is not None and dist <= MAX_HIT_DISTANCE:
        to_obstacle = _angle_deg(axis, _toward_surface(prim, pos))
    return to_obstacle, _angle_deg(axis, tr[-1, :2] - tr[-2, :2])


def yaw_rate_before(traj: np.ndarray, times: np.ndarray, window_s: float = YAW_WINDOW_S) -> float | None:
    """Mean absolute yaw rate [deg/s] over the last ``window_s`` of a trajectory with a heading column.

    ``traj`` is ``(T, 5)`` (x, y, z, speed, heading [rad]), ``times`` its points' times [s]. The heading changes
    between the recorded points inside the window (each wrapped to (-pi, pi]) are summed and divided by the time
    they span. ``None`` when fewer than two points lie in the window.
    """
    tr, t = np.asarray(traj, dtype=np.float64), np.asarray(times, dtype=np.float64)
    if tr.ndim != 2 or tr.shape[1] < 5 or t.shape != (len(tr),):
        raise ValueError(f"need a trajectory (T, 5) with T times, got shapes {tr.shape} and {t.shape}")
    k = np.flatnonzero(t >= t[-1] - window_s - 1e-9)
    if len(k) < 2 or t[-1] <= t[k[0]]:
        return None
    dh = np.diff(tr[k, 4])
    dh = (dh + np.pi) % (2.0 * np.pi) - np.pi
    return float(np.degrees(np.abs(dh).sum() / (t[-1] - t[k[0]])))


def shield_share_before(traj: np.ndarray, times: np.ndarray, window_s: float = YAW_WINDOW_S) -> float | None:
    """Share of the control steps in the last ``window_s`` of a trajectory on which the shield acted.

    ``traj`` is ``(T, 6)``: x, y, z, speed, heading and the share of the steps since the previous point with the
    shield acting (a shielded row's output). The recorded intervals that end inside the window are averaged,
    weighted by their length. ``None`` without that column or without an interval in the window.
    """
    tr, t = np.asarray(traj, dtype=np.float64), np.asarray(times, dtype=np.float64)
    if tr.ndim != 2 or t.shape != (len(tr),):
        raise ValueError(f"need a trajectory (T, C) with T times, got shapes {tr.shape} and {t.shape}")
    if tr.shape[1] < 6 or len(tr) < 2:
        return None
    k = np.flatnonzero(t[1:] > t[-1] - window_s + 1e-9) + 1  # intervals (t[k-1], t[k]] ending in the window
    w = t[k] - t[k - 1]
    return float(np.sum(tr[k, 5] * w) / np.sum(w)) if len(k) and np.sum(w) > 0 else None


def point_times(steps: int, every: int, dt: float) -> np.ndarray:
    """Times [s] of a trial's recorded trajectory points: every ``every``-th control step of ``dt`` and the last."""
    keep = list(range(0, steps + 1, every)) + ([steps] if steps % every else [])
    return np.asarray(keep, dtype=np.float64) * dt


def _crashes(
    out_dir: str,
    rows: list[str] | None,
    speeds: list[float] | None,
    outcome: str | None = "collision",
    with_scene: bool = False,
) -> Iterator[tuple[tuple[str, float], Scene | None, list[np.ndarray], list[np.ndarray], list[str]]]:
    """Per unit of an eval folder: ``(row, speed)``, its scene, the picked trajectories, times and outcomes.

    The scene is ``None`` without picked trials (and for any ``outcome`` but ``collision`` unless ``with_scene``: the
    other breakdowns need none); the times [s] come from :func:`point_times`. ``outcome`` picks the trials
    (``collision``, ``timeout``, ``success``; ``None``: every trial). Except for collisions, the goal rides along as
    each trajectory's last row (its x, y, z; NaN in the other columns).
    """
    files = sorted(glob.glob(os.path.join(out_dir, "units", "*.json")))
    cfg = None
    if os.path.isfile(os.path.join(out_dir, "config.yaml")):
        from shield_nav.evaluation import load_eval_config

        cfg = load_eval_config(os.path.join(out_dir, "config.yaml"))  # its env overrides may set scenes.seed
    if not files:
        raise FileNotFoundError(f"no unit files under {os.path.join(out_dir, 'units')!r}: not an eval.py output")
    for path in files:
        with open(path) as fh:
            unit = json.load(fh)
        if (rows and unit["row"] not in rows) or (speeds and float(unit["speed"]) not in speeds):
            continue
        hits = [t for t in unit["trials"] if outcome is None or t["outcome"] == outcome]
        for t in hits:
            if not t.get("traj"):
                raise ValueError(f"{path}: trial {t.get('trial')} has no trajectory (trajectory_every too large?)")
        if not hits or (outcome != "collision" and not with_scene):
            scene = None
        elif cfg is not None:
            from shield_nav.evaluation import flown_scene

            scene = flown_scene(cfg, unit["family"], int(unit["scene"]))
        else:  # an output folder without its config: the family's default seed
            scene = make_scene(unit["family"], int(unit["scene"]))
        if cfg is not None:
            from shield_nav.evaluation.rollout import nav_config

            every = cfg.trajectory_every
            dt = nav_config(cfg, unit["family"], int(unit["scene"]), float(unit["speed"]), 1).vehicle.command_dt
        else:
            from shield_nav.evaluation.config import EvalConfig

            every, dt = EvalConfig().trajectory_every, VehicleConfig().command_dt
        trajs = [np.asarray(t["traj"]) for t in hits]
        if outcome != "collision":  # the goal rides along as the trajectory's last row (read by timeouts())
            goals = [np.asarray(t["goal"], dtype=np.float64)[:3] for t in hits]
            trajs = [
                np.vstack((tr, np.r_[g, np.full(tr.shape[1] - 3, np.nan)])) for tr, g in zip(trajs, goals, strict=True)
            ]
        times = [point_times(int(t["steps"]), every, dt) for t in hits]
        yield (unit["row"], float(unit["speed"])), scene, trajs, times, [t["outcome"] for t in hits]


def last_progress(times: np.ndarray, dist: np.ndarray, min_progress: float) -> float:
    """Time [s] of a flight's last progress (the stall rule of :class:`shield_nav.safety.escape.StallEscape`).

    The last time its distance to the goal went ``min_progress`` below its best since the previous such time.
    """
    best, at = float(dist[0]), float(times[0])
    for t, d in zip(times[1:], dist[1:], strict=True):
        if d < best - min_progress:
            best, at = float(d), float(t)
    return at


def timeouts(
    out_dir: str,
    rows: list[str] | None = None,
    speeds: list[float] | None = None,
    window_s: float = 5.0,
    min_progress: float = 1.0,
) -> dict[tuple[str, float], dict]:
    """(row, speed) -> how its time-outs end: stalled, or still closing on the goal when the time ran out.

    ``stalled``: no ``min_progress`` of closing on the goal in the last ``window_s`` s (circling or hovering).

    Per (row, speed): ``n`` time-outs, ``stalled``, the median time the stalled flights last made progress
    (``stalled_since_s``, from the start) and their median distance left to the goal (``stalled_left_m``), the closing
    flights' median distance left (``closing_left_m``) and median closing speed over the last window
    (``closing_m_s``), and ``circling``: the time-outs that flew in circles somewhere in the flight
    (:func:`max_turns` at least :data:`CIRCLE_TURNS`; ``None`` for outputs without the heading column). Distances
    are straight-line, from the recorded trajectory points.
    """
    out: dict[tuple[str, float], dict] = {}
    raw: dict[tuple[str, float], list[tuple[bool, float, float, float, bool | None]]] = defaultdict(list)
    for key, _, trajs, times, _ in _crashes(out_dir, rows, speeds, outcome="timeout"):
        raw[key]  # noqa: B018  (rows without time-outs still appear)
        for tr, tm in zip(trajs, times, strict=True):
            dist = np.linalg.norm(tr[:-1, :3] - tr[-1, :3], axis=1)
            since = last_progress(tm, dist, min_progress)
            stalled = tm[-1] - since >= window_s
            k = int(np.searchsorted(tm, tm[-1] - window_s))
            rate = (dist[k] - dist[-1]) / max(tm[-1] - tm[k], 1e-9)
            turns = max_turns(tr[:-1], tm)
            raw[key].append((bool(stalled), since, float(dist[-1]), float(rate),
                             None if turns is None else turns >= CIRCLE_TURNS))  # fmt: skip

    def med(x: list[float]) -> float | None:
        return float(np.median(x)) if x else None

    for key, items in raw.items():
        st = [i for i in items if i[0]]
        cl = [i for i in items if not i[0]]
        out[key] = {"n": len(items), "stalled": len(st), "stalled_since_s": med([i[1] for i in st]),
                    "stalled_left_m": med([i[2] for i in st]), "closing_left_m": med([i[2] for i in cl]),
                    "closing_m_s": med([i[3] for i in cl]),
                    "circling": None if any(i[4] is None for i in items) else sum(bool(i[4]) for i in items),
                    }  # fmt: skip
    return out


def format_timeouts(result: dict[tuple[str, float], dict]) -> str:
    """Markdown table of :func:`timeouts`."""

    def num(x: float | None) -> str:
        return "-" if x is None else f"{x:.1f}"

    lines = ["| row | speed | time-outs | stalled | stalled since [s] | stalled: left [m] | closing: left [m] | "
             "closing [m/s] | circling |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for (row, speed), v in sorted(result.items()):
        cols = [v["stalled_since_s"], v["stalled_left_m"], v["closing_left_m"], v["closing_m_s"]]
        circ = "-" if v["circling"] is None else str(v["circling"])
        lines.append(
            f"| {row} | {speed:g} | {v['n']} | {v['stalled']} | " + " | ".join(map(num, cols)) + f" | {circ} |"
        )
    return "\n".join(lines)


def circling(
    out_dir: str,
    rows: list[str] | None = None,
    speeds: list[float] | None = None,
    window_s: float = CIRCLE_WINDOW_S,
    turns: float = CIRCLE_TURNS,
) -> dict[tuple[str, float], dict[str, list[int]]]:
    """(row, speed) -> outcome -> ``[flights, circling]``: how many flights of each outcome flew in circles.

    A flight circles when its heading turned ``turns`` full turns or more, net, within some ``window_s`` of it
    (:func:`max_turns`). Every outcome of :data:`OUTCOMES` is listed, with zeros where none was flown.

    Raises:
        ValueError: A trajectory lacks the heading column (outputs written before 2026-11-28), or ``turns`` is not
            positive.
    """
    if not (math.isfinite(turns) and turns > 0):
        raise ValueError(f"turns must be finite and > 0, got {turns}")
    out: dict[tuple[str, float], dict[str, list[int]]] = {}
    for key, _, trajs, times, outcomes in _crashes(out_dir, rows, speeds, outcome=None):
        cell = out.setdefault(key, {o: [0, 0] for o in OUTCOMES})
        for tr, tm, oc in zip(trajs, times, outcomes, strict=True):
            if tr.shape[1] < 5:
                raise ValueError(f"{out_dir}: row {key[0]!r} at {key[1]:g} m/s has no heading column; "
                                 "--circling needs an output written since 2026-11-28")  # fmt: skip
            got = max_turns(tr[:-1], tm, window_s)
            c = cell.setdefault(oc, [0, 0])
            c[0] += 1
            c[1] += int(got is not None and got >= turns)
    return out


def sides(
    out_dir: str, rows: list[str] | None = None, speeds: list[float] | None = None, margin: float = SIDE_MARGIN
) -> dict[tuple[str, float, int], list[float]]:
    """(row, speed, scene index) -> each successful flight's share of points beside the volume's lateral sides.

    A recorded point is beside them within ``margin`` [m] of ``y`` = the scene's ``bounds_lo`` or ``bounds_hi`` (the
    sides along the start-to-goal axis); the shares are in trial order.

    Raises:
        ValueError: ``margin`` not finite and positive.
    """
    if not (math.isfinite(margin) and margin > 0):
        raise ValueError(f"margin must be finite and > 0, got {margin}")
    out: dict[tuple[str, float, int], list[float]] = {}
    for (row, speed), scene, trajs, _, _ in _crashes(out_dir, rows, speeds, outcome="success", with_scene=True):
        if scene is None:
            continue
        lo, hi = scene.bounds_lo[1], scene.bounds_hi[1]
        for tr in trajs:
            y = tr[:-1, 1]  # the goal rides along as the last row
            beside = (y - lo <= margin) | (hi - y <= margin)
            out.setdefault((row, speed, scene.index), []).append(float(beside.mean()))
    return out


def format_sides(result: dict[tuple[str, float, int], list[float]], margin: float = SIDE_MARGIN) -> str:
    """Markdown table of :func:`sides`: per scene, the successes and their shares beside the sides."""
    lines = [f"| row | speed | scene | successes | share within {margin:g} m of the sides: min / median / max | "
             "half or more beside |", "|---|---:|---:|---:|---|---:|"]  # fmt: skip
    for (row, speed, scene), v in sorted(result.items()):
        a = np.asarray(v)
        lines.append(f"| {row} | {speed:g} | {scene} | {len(a)} | {a.min():.2f} / {np.median(a):.2f} / {a.max():.2f} "
                     f"| {int((a >= 0.5).sum())} |")  # fmt: skip
    return "\n".join(lines)


def format_circling(result: dict[tuple[str, float], dict[str, list[int]]]) -> str:
    """Markdown table of :func:`circling`: circling flights / flights, per outcome."""
    lines = ["| row | speed | flights | circling | " + " | ".join(o.replace("_", " ") for o in OUTCOMES) + " |",
             "|---|---:|---:|---:|" + "---:|" * len(OUTCOMES)]  # fmt: skip
    for (row, speed), v in sorted(result.items()):
        n = sum(c[0] for c in v.values())
        k = sum(c[1] for c in v.values())
        cols = [f"{v[o][1]} / {v[o][0]}" for o in OUTCOMES]
        lines.append(f"| {row} | {speed:g} | {n} | {k} | " + " | ".join(cols) + " |")
    return "\n".join(lines)


def breakdown(
    out_dir: str, rows: list[str] | None = None, speeds: list[float] | None = None
) -> dict[tuple[str, float], Counter]:
    """(row, speed) -> Counter of hit classes over the collided trials of an eval output folder."""
    out: dict[tuple[str, float], Counter] = defaultdict(Counter)
    for key, scene, trajs, _, _ in _crashes(out_dir, rows, speeds):
        out[key].update()  # rows without collisions still appear
        for tr in trajs:
            out[key][classify_hit(scene, tr[-1, :3])[0]] += 1
    return dict(out)


def bearings(
    out_dir: str, rows: list[str] | None = None, speeds: list[float] | None = None, hfov_deg: float = 87.0
) -> dict[tuple[str, float], dict]:
    """(row, speed) -> approach bearings of its crashes (:func:`approach_bearing`) and their summary.

    Each value holds ``n`` (crashes with a bearing), ``median_deg``, ``in_view`` (the share with a bearing below
    ``hfov_deg / 2``), ``bearings`` (class, degrees) per crash, and from the recorded heading (NaN for outputs
    without it; :func:`camera_angles`) ``in_camera``, the share of crashes whose obstacle lay within ``hfov_deg / 2``
    of the camera's axis, ``blind``, the share that moved more than ``hfov_deg / 2`` off it, and
    ``yaw_rate_deg_s``, the median over the crashes of the mean yaw rate in their last :data:`YAW_WINDOW_S`, and
    for a shielded row's output ``shield_share``, the mean over the crashes of the share of the control steps in
    that window on which the shield acted (:func:`shield_share_before`; NaN without the column).
    """
    if not 0.0 < hfov_deg < 180.0:
        raise ValueError(f"hfov_deg must be in (0, 180), got {hfov_deg}")
    found: dict[tuple[str, float], list] = defaultdict(list)
    cams: dict[tuple[str, float], list] = defaultdict(list)
    blind: dict[tuple[str, float], list] = defaultdict(list)
    rates: dict[tuple[str, float], list] = defaultdict(list)
    acting: dict[tuple[str, float], list] = defaultdict(list)
    for key, scene, trajs, times, _ in _crashes(out_dir, rows, speeds):
        found[key] += []
        for tr, tt in zip(trajs, times, strict=True):
            cls, deg = approach_bearing(scene, tr)
            if deg is not None:
                found[key].append((cls, deg))
            if tr.shape[1] >= 5 and len(tr) >= 2:  # the heading is recorded
                to_obstacle, to_travel = camera_angles(scene, tr)
                if to_obstacle is not None:
                    cams[key].append(to_obstacle)
                if to_travel is not None:
                    blind[key].append(to_travel)
                rate = yaw_rate_before(tr, tt)
                if rate is not None:
                    rates[key].append(rate)
            acted = shield_share_before(tr, tt)
            if acted is not None:
                acting[key].append(acted)
    half = hfov_deg / 2

    def share(x: list) -> float:
        return float((np.array(x) < half).mean()) if x else float("nan")

    out = {}
    for key, items in found.items():
        deg = np.array([d for _, d in items])
        out[key] = {
            "n": len(items),
            "median_deg": float(np.median(deg)) if len(deg) else float("nan"),
            "in_view": share(list(deg)),
            "in_camera": share(cams[key]),
            "blind": 1.0 - share(blind[key]) if blind[key] else float("nan"),
            "yaw_rate_deg_s": float(np.median(rates[key])) if rates[key] else float("nan"),
            "shield_share": float(np.mean(acting[key])) if acting[key] else float("nan"),
            "bearings": items,
        }
    return out


def format_table(result: dict[tuple[str, float], Counter]) -> str:
    """Markdown table: one line per (row, speed), the share of collisions per class (%), n collisions."""
    classes = sorted({c for cnt in result.values() for c in cnt}, key=lambda c: -sum(r[c] for r in result.values()))
    lines = ["| row | speed | n | " + " | ".join(classes) + " |", "|---|---:|---:|" + "---:|" * len(classes)]
    for (row, speed), cnt in sorted(result.items()):
        n = sum(cnt.values())
        cells = [f"{100.0 * cnt[c] / n:.0f}" if n else "-" for c in classes]
        lines.append(f"| {row} | {speed:g} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_bearings(result: dict[tuple[str, float], dict], hfov_deg: float) -> str:
    """Markdown table of :func:`bearings`: per (row, speed) the crashes, median bearing, in-view and beside shares."""
    half = hfov_deg / 2
    lines = [f"| row | speed | n | median bearing (deg) | in view (< {half:g} deg) | beside | in the camera's view | "
             f"moving outside the camera's view | yaw rate, last {YAW_WINDOW_S:g} s (deg/s, median) | "
             f"shield acting, last {YAW_WINDOW_S:g} s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip

    def pct(x: float) -> str:
        return "-" if np.isnan(x) else f"{100 * x:.0f} %"

    def num(x: float) -> str:
        return "-" if np.isnan(x) else f"{x:.0f}"

    for (row, speed), r in sorted(result.items()):
        if r["n"]:
            lines.append(f"| {row} | {speed:g} | {r['n']} | {r['median_deg']:.0f} | {pct(r['in_view'])} | "
                         f"{pct(1 - r['in_view'])} | {pct(r['in_camera'])} | {pct(r['blind'])} | "
                         f"{num(r['yaw_rate_deg_s'])} | {pct(r['shield_share'])} |")  # fmt: skip
        else:
            lines.append(f"| {row} | {speed:g} | 0 | - | - | - | - | - | - | - |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """CLI entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", help="an eval.py output folder (eval_out/<name>)")
    ap.add_argument("--rows", default="", help="comma-separated rows (default: all)")
    ap.add_argument("--speeds", default="", help="comma-separated target speeds (default: all)")
    ap.add_argument("--json", action="store_true", help="print one JSON line instead of the table")
    ap.add_argument("--bearing", action="store_true", help="approach bearings (in view or beside) instead of classes")
    ap.add_argument("--timeouts", action="store_true",
                    help="how the time-outs end (stalled or still closing) instead of the collisions")  # fmt: skip
    ap.add_argument("--circling", action="store_true",
                    help="which flights flew in circles (net heading turns in a window), by outcome")  # fmt: skip
    ap.add_argument("--sides", action="store_true",
                    help="how much of each success flew beside the flight volume's lateral sides")  # fmt: skip
    ap.add_argument("--margin", type=float, default=SIDE_MARGIN,
                    help=f"--sides: the distance that counts as beside them, m (default {SIDE_MARGIN:g})")  # fmt: skip
    ap.add_argument("--hfov", type=float, default=CameraConfig().hfov_deg,
                    help="camera horizontal field of view, deg (default: the camera's)")  # fmt: skip
    a = ap.parse_args(argv)
    if not 0.0 < a.hfov < 180.0:
        ap.error(f"--hfov must be in (0, 180), got {a.hfov}")
    rows = [r for r in a.rows.split(",") if r] or None
    try:
        speeds = [float(s) for s in a.speeds.split(",") if s] or None
    except ValueError:
        ap.error(f"--speeds must be numbers, got {a.speeds!r}")
    if a.timeouts + a.bearing + a.circling + a.sides > 1:
        ap.error("--timeouts, --bearing, --circling and --sides ask different questions; give one")
    if not (math.isfinite(a.margin) and a.margin > 0):
        ap.error(f"--margin must be finite and > 0, got {a.margin}")
    if a.sides:
        res_s = sides(a.out_dir, rows, speeds, a.margin)
        if a.json:
            print(json.dumps([{"row": r, "speed": sp, "scene": sc, "shares": v}
                              for (r, sp, sc), v in sorted(res_s.items())]))  # fmt: skip
        else:
            print(format_sides(res_s, a.margin))
        return
    if a.circling:
        res_c = circling(a.out_dir, rows, speeds)
        if a.json:
            print(json.dumps([{"row": r, "speed": sp, "by_outcome": v} for (r, sp), v in sorted(res_c.items())]))
        else:
            print(format_circling(res_c))
        return
    if a.timeouts:
        res = timeouts(a.out_dir, rows, speeds)
        if a.json:
            print(json.dumps([{"row": r, "speed": sp, **v} for (r, sp), v in sorted(res.items())]))
        else:
            print(format_timeouts(res))
        return
    if a.bearing:
        res = bearings(a.out_dir, rows, speeds, a.hfov)
        if a.json:
            print(json.dumps([{"row": r, "speed": sp, **{k: v[k] for k in ("n", "median_deg", "in_view", "in_camera",
                                                                            "blind", "yaw_rate_deg_s",
                                                                            "shield_share")}}
                              for (r, sp), v in sorted(res.items())]))  # fmt: skip
        else:
            print(format_bearings(res, a.hfov))
        return
    result = breakdown(a.out_dir, rows, speeds)
    if a.json:
        print(
            json.dumps([{"row": r, "speed": s, "n": sum(c.values()), "hits": dict(c)} for (r, s), c in result.items()])
        )
    else:
        print(format_table(result))


if __name__ == "__main__":
    main()
