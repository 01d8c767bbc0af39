"""How much of the expert's route does the depth camera see? A measure of what a depth student can imitate.

``python -m shield_nav.tools.route_view [--scenes benchmark:0-15] [--scene-seed 1150000] [--speed 3] [--steps 600]
[--json]``

flies the privileged planning expert (:mod:`shield_nav.algorithms.expert`, rendering off) and, at every control step of
every env, takes the path it plans (down the geodesic field, 14 m) and asks how far along it the depth camera sees:

* ``seen_m``: the arc length of the path's longest prefix whose samples are all seen
  (:func:`shield_nav.algorithms.expert_paths.visible_samples`: in the frustum and range, line of sight clear by the
  ESDF), capped at the path's length. Samples within ``near_m`` (default 1 m) of the vehicle along the path count as
  seen: the vehicle is passing through them, and there the frustum is narrower than the vehicle's own sway (a sample 0.3
  m ahead leaves the 87 deg view 0.3 m aside);
* the reason its first unseen sample is unseen: ``fov`` (outside the frustum or beyond the range) or ``occluded``
  (inside the frustum, an obstacle on the line of sight);
* ``short``: the share of steps whose ``seen_m`` is below the stopping distance at the current speed,
  ``|v| lag + |v|^2 / (2 brake_accel)`` with the expert's own lag and braking (the profile's planning values), plus
  ``margin_m`` (default 1 m). On such a step the expert acts on route it knows from the map and the camera does not
  show: a depth student that imitates it must guess that part;
* ``away``: the share of steps whose route turns away from the goal: the path's point ``away_at_m`` (3 m) along it
  lies more than 45 deg (horizontally) off the goal's bearing. There the expert takes a way the goal's direction
  does not suggest, chosen by the maze beyond the view; a student that sees the goal's direction and the depth
  image must infer that choice from the visible part alone.

Results are grouped by scene (its family index). The default scenes are the benchmark validation set
(``configs/eval/validation_benchmark.yaml``: the benchmark generator at scene seed 1,150,000), not the test scenes.
"""

from __future__ import annotations

from shield_nav.openmp import limit_spinning

if __name__ == "__main__":  # run as a tool: as train.py does, before torch and numba load libgomp
    limit_spinning()

import argparse
import json
import math
import sys

import numpy as np

from envs.camera.model import camera_poses
from envs.scenes import FAMILIES, make_scene
from shield_nav.algorithms.expert import PlannerController
from shield_nav.algorithms.expert_paths import flight_env, visible_samples
from shield_nav.evaluation.config import EvalError, parse_scenes


def seen_prefix(path: np.ndarray, seen: np.ndarray, in_fov: np.ndarray, near_m: float = 0.0,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Arc length (N,) of each path's seen prefix, whether its first unseen sample is occluded, whether it is whole.

    Returns ``(seen_m, occluded, whole)``: ``whole`` (N,) bool marks paths seen to their last sample.

    Args:
        path: Paths (N, K+1, 3).
        seen: (N, K+1) bool, samples the camera sees (sample 0 always seen).
        in_fov: (N, K+1) bool, samples inside the frustum and range, whatever the line of sight.
        near_m: Samples closer than this along the path count as seen [m].

    A path seen to its end has the whole length and is not occluded.
    """
    seglen = np.linalg.norm(np.diff(path, axis=1), axis=2)
    cum = np.concatenate((np.zeros((len(path), 1)), np.cumsum(seglen, axis=1)), axis=1)
    seen = seen | (cum < near_m)
    prefix = np.logical_and.accumulate(seen, axis=1)
    last = prefix.sum(axis=1) - 1  # index of the last sample of the seen prefix
    rows = np.arange(len(path))
    whole = last == path.shape[1] - 1
    first_unseen = np.minimum(last + 1, path.shape[1] - 1)
    occluded = ~whole & in_fov[rows, first_unseen]
    return cum[rows, last], occluded, whole


def measure(family: str, indices: list[int], scene_seed: int | None, speed: float, steps: int, num_envs: int,
            seed: int = 0, margin_m: float = 1.0, near_m: float = 1.0, away_at_m: float = 3.0) -> dict:  # fmt: skip
    """Fly the expert ``steps`` control steps in ``num_envs`` envs of each scene; per-scene view statistics."""
    from envs.navigation import NavigationEnv
    from shield_nav.algorithms.baselines import BaselineConfig

    scenes = {}
    for scene in indices:  # one env per scene, so every scene gets the same number of samples
        env = flight_env(family, [scene], scene_seed, speed, num_envs, seed)
        planner = PlannerController(BaselineConfig())
        ec = planner.ec
        ids = np.zeros(num_envs, dtype=np.int64)

        def esdf(pts: np.ndarray, env: NavigationEnv = env, ids: np.ndarray = ids) -> np.ndarray:
            return env.field_stack.esdf(np.repeat(ids, pts.shape[1]), pts.reshape(-1, 3)).reshape(pts.shape[:2])

        seen_all, occ_all, whole_all, short_all, away_all = [], [], [], [], []
        for _ in range(steps):
            cmd = planner.commands(env)
            path = planner.last["path"]
            cam_pos, R_wc = camera_poses(env.cfg.camera, env.local_pos, env.vehicles.R_wb)
            seen = visible_samples(path, cam_pos, R_wc, env.cfg.camera, esdf, ec.los_step)
            in_fov = visible_samples(path, cam_pos, R_wc, env.cfg.camera, _no_obstacles, ec.los_step)
            seen_m, occluded, whole = seen_prefix(path, seen, in_fov, near_m)
            v = np.linalg.norm(env.vehicles.vel_w, axis=1)
            stop = v * ec.lag_s + v**2 / (2.0 * ec.brake_accel) + margin_m
            seen_all.append(seen_m)
            occ_all.append(occluded)
            whole_all.append(whole)
            short_all.append(seen_m < stop)
            away_all.append(route_away(path, env.goal_buf - env.local_pos, away_at_m))
            env.step(np.zeros((num_envs, 4)), commands=cmd)
        s = np.concatenate(seen_all)
        occ = np.concatenate(occ_all)
        unseen_end = ~np.concatenate(whole_all)
        scenes[str(scene)] = {
            "samples": len(s),
            "seen_m_median": float(np.median(s)),
            "seen_m_p10": float(np.percentile(s, 10)),
            "short": float(np.concatenate(short_all).mean()),
            "occluded_share": float(occ[unseen_end].mean()) if unseen_end.any() else 0.0,
            "away": float(np.concatenate(away_all).mean()),
        }
        print(f"[route_view] {family}/{scene} at {speed:g} m/s: {len(s)} samples, seen route median "
              f"{scenes[str(scene)]['seen_m_median']:.1f} m ({len(scenes)} of {len(indices)} scenes)",
              file=sys.stderr, flush=True)  # fmt: skip
    return {"family": family, "scene_seed": scene_seed, "speed": speed, "steps": steps, "num_envs": num_envs,
            "margin_m": margin_m, "near_m": near_m, "away_at_m": away_at_m, "scenes": scenes}  # fmt: skip


def _no_obstacles(pts: np.ndarray) -> np.ndarray:
    """An ESDF of empty space: :func:`visible_samples` with it tests the frustum and range only."""
    return np.full(pts.shape[:2], np.inf)


def route_away(path: np.ndarray, to_goal: np.ndarray, at_m: float = 3.0, limit_deg: float = 45.0) -> np.ndarray:
    """(N,) bool: the path's sample nearest ``at_m`` along it lies more than ``limit_deg`` off ``to_goal``'s bearing.

    Paths (N, K+1, 3) start at the vehicle; ``to_goal`` (N, 3) is the goal minus the vehicle's position.
    """
    seglen = np.linalg.norm(np.diff(path, axis=1), axis=2)
    cum = np.concatenate((np.zeros((len(path), 1)), np.cumsum(seglen, axis=1)), axis=1)
    k = np.argmin(np.abs(cum - at_m), axis=1)
    return bearing_deg(path[np.arange(len(path)), k] - path[:, 0], to_goal) > limit_deg


def bearing_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Horizontal angle (N,) between vectors ``a`` and ``b`` (N, 3) in degrees, 0-180 (0 where either is vertical)."""
    a2, b2 = a[:, :2], b[:, :2]
    na, nb = np.linalg.norm(a2, axis=1), np.linalg.norm(b2, axis=1)
    cos = np.einsum("ij,ij->i", a2, b2) / np.maximum(na * nb, 1e-12)
    return np.where((na > 1e-9) & (nb > 1e-9), np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 0.0)


def format_table(res: dict) -> str:
    """Markdown table of :func:`measure` output, one row per scene."""
    lines = ["| scene | samples | seen path, median m | seen path, 10th pct m | steps seeing less than the stop "
             "distance | unseen by occlusion (not FOV) | route > 45 deg off the goal |",
             "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for i, r in res["scenes"].items():
        shares = " | ".join(f"{100 * r[k]:.0f} %" for k in ("short", "occluded_share", "away"))
        lines.append(f"| {res['family']}/{i} | {r['samples']} | {r['seen_m_median']:.1f} | {r['seen_m_p10']:.1f} | "
                     f"{shares} |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.route_view", description=__doc__.split("\n")[0])
    ap.add_argument(
        "--scenes", default="benchmark:0-15", help="FAMILY or FAMILY:INDICES, as eval.py (default benchmark:0-15)"
    )
    ap.add_argument(
        "--scene-seed",
        type=lambda t: None if t == "default" else int(t),
        default=1150000,
        help="scene generator seed, or 'default' for the family's own (default 1150000: the benchmark validation "
        "scenes)",
    )
    ap.add_argument("--speed", type=float, default=3.0, help="target speed [m/s] (default 3)")
    ap.add_argument("--steps", type=int, default=600, help="control steps of 10 ms (default 600)")
    ap.add_argument("--num-envs", type=int, default=32, help="parallel envs (default 32)")
    ap.add_argument("--margin", type=float, default=1.0, help="added to the stopping distance [m] (default 1)")
    ap.add_argument(
        "--near", type=float, default=1.0, help="path within this of the vehicle counts as seen [m] (default 1)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print one JSON line instead of a table")
    args = ap.parse_args(argv)
    try:
        sel = parse_scenes(args.scenes)  # the eval CLI's syntax: FAMILY (all of it) or FAMILY:INDICES
        family, indices = sel.family, sel.indices or list(range(FAMILIES[sel.family].size))
    except EvalError as err:
        ap.error(str(err))
    bad_speed = not (args.speed > 0 and math.isfinite(args.speed))
    if args.steps < 1 or args.num_envs < 1 or bad_speed or args.margin < 0 or args.near < 0:
        ap.error(f"need --steps >= 1, --num-envs >= 1, a finite --speed > 0, --margin >= 0 and --near >= 0, got "
                 f"{args.steps}, {args.num_envs}, {args.speed}, {args.margin}, {args.near}")  # fmt: skip
    try:  # a family, scene or seed that does not exist is named before any flight
        for i in indices:
            make_scene(family, i, args.scene_seed)
    except ValueError as err:
        ap.error(str(err))
    res = measure(
        family, indices, args.scene_seed, args.speed, args.steps, args.num_envs, args.seed, args.margin, args.near
    )
    if args.json:
        print(json.dumps(res))
    else:
        print(f"expert's route in view, {res['family']} scenes (seed {res['scene_seed']}), {res['speed']:g} m/s, "
              f"{res['num_envs']} envs x {res['steps']} steps")  # fmt: skip
        print(format_table(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
