"""HOCBF shield cost: replay recorded states of the scripted pole/wall flights through every solver.

``python -m shield_nav.bench shield --json``. The states (pose, velocity, depth image, raw command) are recorded
from the shielded scripted flights at 3/5/7/9 m/s, so the QPs are the ones the shield really meets. Reported per
solver: QP time over the steps where the shield was active (mean, p99, max) and the active fraction; separately the
point-cloud + constraint-selection cost and the whole shield step (point cloud, selection, QP, conversion back).
"""

from __future__ import annotations

import time

import numpy as np
import qpsolvers

from envs.camera import CameraConfig, depth_to_points
from shield_nav.bench.common import emit, machine, parser
from shield_nav.scripted import fly
from shield_nav.shield import HOCBFShield, ShieldConfig, accel_from_command

PAPER = {"mean_us": 90.61, "max_us": 384.5, "active_fraction": 0.1306}


def _stats(x: np.ndarray) -> dict:
    if len(x) == 0:
        return {"mean_us": None, "p99_us": None, "max_us": None}
    return {
        "mean_us": round(float(np.mean(x)), 2),
        "p99_us": round(float(np.percentile(x, 99)), 2),
        "max_us": round(float(np.max(x)), 2),
    }


def record(duration: float = 4.5) -> list:
    """States (pos, vel, R, cmd, depth) per step of the shielded scripted flights, one entry per vehicle-step."""
    states = []
    for kind in ("pole", "wall"):
        log = fly(kind, [3.0, 5.0, 7.0, 9.0], shielded=True, duration=duration, record_states=True)
        for pos, vel, r_wb, cmd, depth in log.states:
            for i in range(len(pos)):
                states.append((pos[i : i + 1], vel[i : i + 1], r_wb[i : i + 1], cmd[i : i + 1], depth[i : i + 1]))
    return states


def main(argv: list[str]) -> dict:
    """Record, then replay the states through each installed solver."""
    p = parser("shield", __doc__.splitlines()[0])
    p.add_argument("--solvers", nargs="+", default=None, help="qpsolvers backends (default: every installed one)")
    p.add_argument("--repeats", type=int, default=2, help="replays of the recorded states per solver")
    args = p.parse_args(argv)
    states = record()
    cam = CameraConfig()
    solvers = args.solvers or [s for s in ("daqp", "quadprog", "proxqp", "osqp") if s in qpsolvers.available_solvers]
    per_solver = []
    whole = None
    for solver in solvers:
        shield = HOCBFShield(ShieldConfig(solver=solver), cam)
        solve, total, active = [], [], []
        for rep in range(args.repeats + 1):
            for pos, vel, r_wb, cmd, depth in states:
                out = shield.filter(cmd, pos, vel, depth=depth, R_wb=r_wb)
                if rep == 0:
                    continue  # warm-up pass (numba compilation, solver imports)
                active.append(bool(out.active[0]))
                total.append(out.total_us[0])
                if out.active[0]:
                    solve.append(out.solve_us[0])
        row = {"solver": solver, **_stats(np.array(solve)), "active_fraction": round(float(np.mean(active)), 4)}
        per_solver.append(row)
        if whole is None:
            whole = {"solver": solver, **_stats(np.array(total))}
        if not args.json:
            print(row)
    # Point cloud + selection alone (no QP), over the same states.
    shield = HOCBFShield(ShieldConfig(), cam)
    sel = []
    for rep in range(2):
        for pos, vel, r_wb, cmd, depth in states:
            a_raw = accel_from_command(cmd)[0]
            t0 = time.perf_counter()
            pts = depth_to_points(depth[0], pos[0], r_wb[0], cam)
            shield.constraints(pts, pos[0], vel[0], a_raw)
            if rep:
                sel.append(1e6 * (time.perf_counter() - t0))
    result = {
        "benchmark": "shield",
        "states": len(states),
        "solvers": per_solver,
        "pointcloud_selection": _stats(np.array(sel)),
        "whole_step": whole,
        "paper": PAPER,
        "goal": {"qp_mean_us": 30, "qp_p99_us": 100, "whole_step_mean_us": 100},
        **machine(),
    }
    emit(result, args.json)
    return result
