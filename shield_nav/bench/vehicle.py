"""Vehicle stepping throughput: N quadrotors flying random attitude commands, no obstacles.

``python -m shield_nav.bench vehicle --json``. One policy step is one 10 ms command period: ``substeps`` MuJoCo
steps, each with the full PX4-style inner loop and motor model for every vehicle. ``policy_steps_per_s`` counts
vehicle-steps (N per batched step).
"""

from __future__ import annotations

import time

import numpy as np

from envs.vehicle.config import VehicleConfig
from envs.vehicle.vehicles import Vehicles
from shield_nav.bench.common import emit, machine, parser


def measure(num: int, seconds: float, seed: int = 0) -> dict:
    """Time batched steps of ``num`` vehicles under random attitude commands (resampled every 0.2 s)."""
    cfg = VehicleConfig()
    veh = Vehicles(num, cfg)
    rng = np.random.default_rng(seed)
    cmd = np.zeros((num, 4))

    def sample() -> None:
        cmd[:, 0] = rng.uniform(0.8, 1.3, num) * cfg.gravity
        cmd[:, 1:3] = rng.uniform(-0.35, 0.35, (num, 2))
        cmd[:, 3] = rng.uniform(-np.pi, np.pi, num)

    sample()
    for _ in range(5):  # warm-up
        veh.step(cmd)
    steps = 0
    t0 = time.perf_counter()
    while True:
        if steps % 20 == 0:
            sample()
            # Keep vehicles in a sane envelope so long runs do not drift far or crash into the floor.
            veh.reset(np.arange(num), np.tile([0.0, 0.0, 1.0], (num, 1)))
        veh.step(cmd)
        steps += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds and steps >= 20:
            break
    return {
        "num_envs": num,
        "policy_steps_per_s": round(num * steps / elapsed, 1),
        "batched_step_ms": round(1e3 * elapsed / steps, 3),
        "physics_substeps": cfg.substeps,
        "physics_hz": round(1.0 / cfg.physics_dt),
    }


def main(argv: list[str]) -> dict:
    """Run the benchmark for N = 1, 64, 256 (or ``--num-envs``)."""
    p = parser("vehicle", __doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, nargs="+", default=[1, 64, 256])
    p.add_argument("--seconds", type=float, default=3.0, help="timing window per N")
    args = p.parse_args(argv)
    runs = []
    for n in args.num_envs:
        r = measure(n, args.seconds)
        runs.append(r)
        if not args.json:
            print(f"N={n:4d}: {r['policy_steps_per_s']:>10.0f} vehicle-steps/s ({r['batched_step_ms']} ms per batch)")
    last = runs[-1]
    result = {
        "benchmark": "vehicle",
        "num_envs": last["num_envs"],
        "policy_steps_per_s": last["policy_steps_per_s"],
        "physics_substeps": last["physics_substeps"],
        "goal_policy_steps_per_s": 20000,
        "runs": runs,
        **machine(),
    }
    emit(result, args.json)
    return result
