"""Where does the privileged expert's speed go? The gap between the target speed and the flown one, split by cause.

``python -m shield_nav.tools.speed_budget [--scenes train_shapes:8-15] [--scene-seed default] [--speed 7] [--steps 600]
[--num-envs 32] [--set KEY=VALUE ...] [--json]``

flies the planning expert (:mod:`shield_nav.algorithms.expert`, rendering off, envs reset as their episodes end) and, at
every control step of every env, reads three speeds at the tracker's reference sample (``round(|v| lag_s / ds)`` along
the planned path):

* ``curvature_cap``: ``min(target, sqrt(lat_accel / kappa))``, what the bends of the path allow;
* ``profile``: the speed profile there (the curvature caps, any clearance or camera cap, and the backward braking
  pass): what the expert asks for;
* ``vehicle``: ``|v|``, what the vehicle flies.

The means over all steps (the start from hover included, as ``mean_speed`` of the evaluation includes it) split the
target's shortfall into ``bends = target - curvature_cap``, ``braking = curvature_cap - profile`` (the braking pass
and the other caps) and ``tracking = profile - vehicle`` (the velocity loop's lag and drag error, the starts, the
re-acceleration out of bends). ``--set`` takes :class:`shield_nav.algorithms.expert_config.ExpertConfig` keys (``--set
drag_ff=1``), so a variant's budget is read beside the default's in a few seconds, before an evaluation of its success.

It also measures how far the vehicle strays from what it planned: ``deviation_mean`` and ``deviation_p95``, the
distance from the vehicle to the path the expert planned ``DEVIATION_DELAY_S`` (0.3 s) earlier in the same
episode, and ``clear_p05``, the 5th percentile of that path's own clearance (ESDF) at its sample nearest the
vehicle. Where the deviation comes near the clearance beyond the vehicle radius, the tracker, not the path, sets
how fast the expert can fly safely.
"""

from __future__ import annotations

from shield_nav.openmp import limit_spinning

if __name__ == "__main__":  # run as a tool: as train.py does, before torch and numba load libgomp
    limit_spinning()

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from envs.config import ConfigError, load_config
from envs.scenes import FAMILIES, make_scene
from shield_nav.algorithms.expert_paths import polyline_distance
from shield_nav.evaluation.config import EvalError, parse_scenes


def reference_speeds(last: dict[str, np.ndarray], speed: np.ndarray, target: np.ndarray, ec: Any) -> np.ndarray:
    """(N, 3) curvature cap, profile and vehicle speed at each env's reference sample.

    Args:
        last: :attr:`shield_nav.algorithms.expert.PlannerController.last` after a ``commands`` call (``kappa``,
            ``speed`` and the tracker's reference sample ``k_ref``).
        speed: |v| (N,) of the vehicles at that call.
        target: Target speeds (N,).
        ec: The expert's :class:`shield_nav.algorithms.expert_config.ExpertConfig`.
    """
    prof, kappa = last["speed"], last["kappa"]
    rows = np.arange(len(speed))
    k = last["k_ref"]
    cap = np.minimum(target, np.sqrt(ec.lat_accel / np.maximum(kappa[rows, k], 1e-9)))
    return np.stack((cap, prof[rows, k], speed), axis=1)


DEVIATION_DELAY_S = 0.3
"""How long before a step the path is planned that the step's deviation is measured against [s]."""


def budget(samples: np.ndarray, target: float) -> dict[str, float]:
    """Means of (M, 3) reference speeds and the shortfall split ``bends``, ``braking``, ``tracking`` [m/s]."""
    cap, prof, veh = (float(x) for x in samples.mean(axis=0))
    return {
        "target": target,
        "curvature_cap": cap,
        "profile": prof,
        "vehicle": veh,
        "bends": target - cap,
        "braking": cap - prof,
        "tracking": prof - veh,
        "profile_below_085": float((samples[:, 1] < 0.85 * target).mean()),
    }


def measure(family: str, indices: list[int], scene_seed: int | None, speed: float, steps: int, num_envs: int,
            seed: int = 0, expert: dict[str, Any] | None = None) -> dict:  # fmt: skip
    """Fly the expert ``steps`` control steps in ``num_envs`` envs over the scenes; the speed budget of all steps."""
    from shield_nav.algorithms.baselines import BaselineConfig
    from shield_nav.algorithms.expert import PlannerController
    from shield_nav.algorithms.expert_paths import flight_env

    cfg = load_config(BaselineConfig, overrides={f"expert.{k}": v for k, v in (expert or {}).items()})
    env = flight_env(family, indices, scene_seed, speed, num_envs, seed)
    planner = PlannerController(cfg)
    delay = max(1, round(DEVIATION_DELAY_S / env.cfg.vehicle.command_dt))
    samples, history, dev, clear = [], [], [], []
    for step in range(steps):
        v = np.linalg.norm(env.vehicles.vel_w, axis=1)
        cmd = planner.commands(env)
        samples.append(reference_speeds(planner.last, v, env.target_speed_buf, planner.ec))
        history.append((planner.last["path"], planner.last["clear"]))
        if len(history) > delay:
            old_path, old_clear = history.pop(0)
            same = env.episode_length_buf >= delay  # planned in this episode
            if same.any():
                d, k = polyline_distance(env.local_pos[same], old_path[same])
                dev.append(d)
                clear.append(old_clear[same][np.arange(int(same.sum())), k])
        env.step(np.zeros((num_envs, 4)), commands=cmd)
        if (step + 1) % 200 == 0:
            print(f"[speed_budget] {step + 1} of {steps} steps", file=sys.stderr, flush=True)
    out = budget(np.concatenate(samples), float(speed))
    if dev:  # None (JSON null) when no step is DEVIATION_DELAY_S into its episode
        dev_all, clear_all = np.concatenate(dev), np.concatenate(clear)
        stray = {"deviation_mean": float(dev_all.mean()), "deviation_p95": float(np.percentile(dev_all, 95)),
                 "clear_p05": float(np.percentile(clear_all, 5))}  # fmt: skip
    else:
        stray = dict.fromkeys(("deviation_mean", "deviation_p95", "clear_p05"))
    out.update(stray)
    if not all(x is None or math.isfinite(x) for x in out.values()):
        raise FloatingPointError(f"speed_budget: a non-finite mean in {out}")
    return {"family": family, "scenes": list(indices), "scene_seed": scene_seed, "steps": steps,
            "num_envs": num_envs, "expert": dict(expert or {}), **out}  # fmt: skip


def parse_key_value(text: str) -> tuple[str, Any]:
    """``--set KEY=VALUE`` of the expert tools (here and ``bench expert``): the key and its YAML-parsed value."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"--set takes KEY=VALUE, got {text!r}")
    import yaml

    return key, yaml.safe_load(value)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.speed_budget", description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="train_shapes:8-15", help="FAMILY or FAMILY:INDICES, as eval.py "
                    "(default train_shapes:8-15, the validation scenes)")  # fmt: skip
    ap.add_argument("--scene-seed", type=lambda t: None if t == "default" else int(t), default=None,
                    help="scene generator seed (default: the family's own)")  # fmt: skip
    ap.add_argument("--speed", type=float, default=7.0, help="target speed [m/s] (default 7)")
    ap.add_argument("--steps", type=int, default=600, help="control steps of 10 ms (default 600)")
    ap.add_argument("--num-envs", type=int, default=32, help="parallel envs (default 32)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--set", dest="sets", type=parse_key_value, action="append", default=[], metavar="KEY=VALUE",
                    help="an ExpertConfig key (repeat --set for several)")  # fmt: skip
    ap.add_argument("--json", action="store_true", help="print one JSON line instead of a table")
    args = ap.parse_args(argv)
    try:
        sel = parse_scenes(args.scenes)
        family, indices = sel.family, sel.indices or list(range(FAMILIES[sel.family].size))
    except EvalError as err:
        ap.error(str(err))
    if args.steps < 1 or args.num_envs < 1 or not (args.speed > 0 and math.isfinite(args.speed)):
        ap.error(f"need --steps >= 1, --num-envs >= 1 and a finite --speed > 0, got {args.steps}, {args.num_envs}, "
                 f"{args.speed}")  # fmt: skip
    expert = dict(args.sets)
    try:  # a bad expert key or value, scene or seed is named before any flight
        from shield_nav.algorithms.baselines import BaselineConfig

        load_config(BaselineConfig, overrides={f"expert.{k}": v for k, v in expert.items()})
        for i in indices:
            make_scene(family, i, args.scene_seed)
    except (ConfigError, ValueError) as err:
        ap.error(str(err))
    res = measure(family, indices, args.scene_seed, args.speed, args.steps, args.num_envs, args.seed, expert)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"expert's speed budget, {family}:{','.join(map(str, indices))}, {args.speed:g} m/s, "
              f"{args.num_envs} envs x {args.steps} steps{'' if not expert else f', {expert}'}")  # fmt: skip
        head = ("target", "curvature cap", "profile", "vehicle", "lost to bends", "to braking and other caps",
                "to tracking", "deviation mean / p95 [m]", "path clearance p05 [m]")  # fmt: skip
        print("| " + " | ".join(head) + " |")
        print("|" + "---:|" * len(head))
        cells = [f"{res[k]:.2f}" for k in ("target", "curvature_cap", "profile", "vehicle", "bends", "braking",
                                           "tracking")]  # fmt: skip
        if res["deviation_mean"] is None:
            cells += ["-", "-"]
        else:
            cells += [f"{res['deviation_mean']:.2f} / {res['deviation_p95']:.2f}", f"{res['clear_p05']:.2f}"]
        print(" | ".join(["", *cells, ""]).strip())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
