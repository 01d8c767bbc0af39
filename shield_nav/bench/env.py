"""Task throughput: N envs stepping with random actions, depth rendered at the full 100 Hz, randomization on.

``python -m shield_nav.bench env --json``. Reports env-steps/s, the share of time spent rendering depth (and the
other stages, from a cProfile pass), and the peak resident memory.
"""

from __future__ import annotations

import cProfile
import pstats
import time

import numpy as np

from envs.navigation import NavigationEnv
from shield_nav.bench.common import emit, machine, parser, peak_rss_mb

STAGES = {
    "depth_render": ("renderer.py", "render"),
    "depth_noise": ("noise.py", "apply"),
    "vehicle_step": ("vehicles.py", "step"),
    "fields": ("lookup.py", "query"),
    "resets": ("env.py", "_reset_idx"),
    "scene_memory": ("memory.py", "push"),  # storing frames (when env.scene_memory.enabled)
    "scene_memory_read": ("memory.py", "observe"),  # the sector read-out
}


def measure(num: int, seconds: float, overrides: list[str] | None = None) -> dict:
    """Step ``num`` envs for ``seconds`` with uniform random actions; profile a second window for the split.

    ``overrides`` are env config ``KEY=VALUE`` strings (e.g. ``scene_memory.enabled=true``), applied last.
    """
    extra = dict(o.split("=", 1) for o in overrides or [])
    env = NavigationEnv(num_envs=num, overrides={"randomization.depth_noise.frame_rate_hz": 0.0, **extra})
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def act() -> np.ndarray:
        a = rng.uniform(-0.3, 0.3, (num, 4))
        a[:, 2] += 0.3  # pitch forward a little so vehicles travel and episodes end
        return a

    for _ in range(5):
        env.step(act())
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 5:
        env.step(act())
        steps += 1
    elapsed = time.perf_counter() - t0
    prof = cProfile.Profile()
    prof.enable()
    pst = 0
    t1 = time.perf_counter()
    while time.perf_counter() - t1 < min(seconds, 3.0) or pst < 5:
        env.step(act())
        pst += 1
    prof.disable()
    total = time.perf_counter() - t1
    stats = pstats.Stats(prof).stats
    split = {}
    for name, (file, func) in STAGES.items():
        cum = sum(v[3] for k, v in stats.items() if k[0].endswith(file) and k[2] == func)
        split[name] = round(cum / total, 3)
    split["other"] = round(max(0.0, 1.0 - sum(split.values())), 3)
    return {
        "num_envs": num,
        "env_steps_per_s": round(num * steps / elapsed, 1),
        "batched_step_ms": round(1e3 * elapsed / steps, 2),
        "depth_share": split["depth_render"],
        "profile_split": split,
    }


def main(argv: list[str]) -> dict:
    """Run for N = 64 and 256 (or ``--num-envs``)."""
    p = parser("env", __doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, nargs="+", default=[64, 256])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                   help="env config overrides, e.g. scene_memory.enabled=true")  # fmt: skip
    args = p.parse_args(argv)
    bad = [o for o in args.set if "=" not in o]
    if bad:
        p.error(f"--set takes KEY=VALUE, got {bad}")
    runs = []
    for n in args.num_envs:
        r = measure(n, args.seconds, args.set)
        runs.append(r)
        if not args.json:
            print(r)
    last = runs[-1]
    result = {
        "benchmark": "env",
        "overrides": args.set,
        "num_envs": last["num_envs"],
        "env_steps_per_s": last["env_steps_per_s"],
        "depth_share": last["depth_share"],
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "goal_env_steps_per_s": 4000,
        "runs": runs,
        **machine(),
    }
    emit(result, args.json)
    return result
