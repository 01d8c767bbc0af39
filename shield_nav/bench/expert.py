"""Cost per label of the privileged experts: ``python -m shield_nav.bench expert --json``.

A batch of envs on the ablation scenes (``--scenes``: another family or selection, e.g. ``benchmark:14-15`` for
the box mazes, where the expert descends the narrow field; rendering off) is flown a few hundred steps by the
planning expert; each control step's expert call (path trace, smoothing, speed profile, tracker) is timed, and so
is the scripted oracle's on the same states. Reported: microseconds per env per label for both, the env step without
rendering, for scale, and ``narrow_share``, the share of labels on the narrow field.
``--set KEY=VALUE`` (repeatable) times a variant of the expert
(:class:`shield_nav.algorithms.expert_config.ExpertConfig` keys).
"""

from __future__ import annotations

import time

import numpy as np

from envs.config import ConfigError, load_config
from envs.navigation import NavigationEnv
from envs.scenes import FAMILIES
from shield_nav.algorithms.baselines import BaselineConfig, OracleConfig, OracleController
from shield_nav.algorithms.expert import PlannerController
from shield_nav.bench.common import emit, machine, parser
from shield_nav.evaluation.config import EvalError, parse_scenes
from shield_nav.tools.speed_budget import parse_key_value


def main(argv: list[str]) -> dict:
    """Fly the expert, time its labels and the oracle's on the same states."""
    p = parser("expert", __doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=50)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--speed", type=float, default=7.0)
    p.add_argument("--scenes", default="ablation", help="FAMILY or FAMILY:INDICES, as eval.py (default: ablation)")
    p.add_argument("--set", dest="sets", type=parse_key_value, action="append", default=[], metavar="KEY=VALUE",
                   help="an ExpertConfig key of the timed expert (repeat --set for several)")  # fmt: skip
    args = p.parse_args(argv)
    expert = dict(args.sets)
    try:  # a bad key or value is named before any flight
        cfg = load_config(BaselineConfig, overrides={f"expert.{k}": v for k, v in expert.items()})
    except ConfigError as err:
        p.error(str(err))
    try:
        sel = parse_scenes(args.scenes)
    except EvalError as err:
        p.error(str(err))
    indices = sel.indices or list(range(FAMILIES[sel.family].size))
    env = NavigationEnv(num_envs=args.num_envs, **{
        "scenes.family": sel.family, "scenes.indices": indices, "render_depth": False,
        "curriculum.enabled": False, "episode.target_speeds": [args.speed], "episode.speed_range": []})  # fmt: skip
    env.reset(seed=0)
    planner = PlannerController(cfg)
    oracle = OracleController(BaselineConfig(oracle=OracleConfig(episode_goal=True, field_radius=0.5)))
    planner.commands(env)
    oracle.commands(env)  # build the inflated fields outside the timing
    t_exp, t_orc, t_env, narrow = [], [], [], []
    for _ in range(args.steps):
        t0 = time.perf_counter()
        cmd = planner.commands(env)
        t1 = time.perf_counter()
        oracle.commands(env)
        t2 = time.perf_counter()
        env.step(np.zeros((args.num_envs, 4)), commands=cmd)
        t3 = time.perf_counter()
        t_exp.append(t1 - t0)
        t_orc.append(t2 - t1)
        t_env.append(t3 - t2)
        narrow.append(planner.fallback.mean())
    n = args.num_envs
    result = {
        "benchmark": "expert",
        "num_envs": n,
        "steps": args.steps,
        "speed": args.speed,
        "scenes": f"{sel.family}:{','.join(map(str, indices))}",
        "narrow_share": round(float(np.mean(narrow)), 4),
        "expert": expert,
        "expert_us_per_label": round(1e6 * float(np.mean(t_exp)) / n, 2),
        "oracle_us_per_label": round(1e6 * float(np.mean(t_orc)) / n, 2),
        "env_step_no_render_us_per_env": round(1e6 * float(np.mean(t_env)) / n, 2),
        **machine(),
    }
    emit(result, args.json)
    return result
