"""HOCBF shield cost: replay recorded states of the scripted pole/wall flights through every solver.

``python -m shield_nav.bench shield --json``. The states (pose, velocity, depth image, raw command) are recorded
from the shielded scripted flights at 3/5/7/9 m/s, so the QPs are the ones the shield really meets. Reported per
solver: QP time over the steps where the shield was active (mean, p99, max) and the active fraction; separately the
point-cloud + constraint-selection cost and the whole shield step (point cloud, selection, QP, conversion back).
``formulations`` compares, in the same run, the whole step and the QP of the default shield against the paper's
formulation (``PAPER_FORMULATION``: one-shot selection, no lag, p1 = p2 = 4 /s), the backup-barrier option
(``barrier: backup``), the default without its local map (``map_seconds: 0``) and the setting for a noisy sensor
(``depth_filter: median_cross``, ``map_radius: 3``), since absolute CPU times move 2-3x
between machines of this kind; they replay the states in lockstep, so a slow spell hits all alike.
"""

from __future__ import annotations

import time

import numpy as np
import qpsolvers

from envs.camera import CameraConfig, depth_to_points
from shield_nav.bench.common import emit, machine, parser
from shield_nav.evaluation.config import BUILTIN_ROWS
from shield_nav.safety.shield import HOCBFShield, ShieldConfig, accel_from_command
from shield_nav.tools.scripted import fly

PAPER = {"mean_us": 90.61, "max_us": 384.5, "active_fraction": 0.1306}
PAPER_FORMULATION = dict(BUILTIN_ROWS["full_paper_shield"].shield_overrides)
"""The paper's shield as a switch, the evaluation row ``full_paper_shield``'s overrides (configs/eval/rows.yaml): select
once at the raw command, rows at the current state, the current image only, our first gains and radius."""


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
    for k, kind in enumerate(("pole", "wall")):
        log = fly(kind, [3.0, 5.0, 7.0, 9.0], shielded=True, duration=duration, record_states=True)
        for pos, vel, r_wb, cmd, depth in log.states:
            for i in range(len(pos)):
                vid = np.array([4 * k + i])  # per-flight id: the lag's velocity history follows each flight
                states.append((pos[i : i + 1], vel[i : i + 1], r_wb[i : i + 1], cmd[i : i + 1], depth[i : i + 1], vid))
    return states


def replay(shield: HOCBFShield, states: list, repeats: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """QP times of the active steps, whole-step times and activity over ``repeats`` replays (after a warm-up)."""
    solve, total, active = [], [], []
    for rep in range(repeats + 1):
        shield.reset()
        for pos, vel, r_wb, cmd, depth, vid in states:
            out = shield.filter(cmd, pos, vel, depth=depth, R_wb=r_wb, ids=vid)
            if rep == 0:
                continue  # warm-up pass (numba compilation, solver imports)
            active.append(bool(out.active[0]))
            total.append(out.total_us[0])
            if out.active[0]:
                solve.append(out.solve_us[0])
    return np.array(solve), np.array(total), np.array(active)


def replay_interleaved(
    shields: dict[str, HOCBFShield], states: list, repeats: int
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``replay`` for several shields in lockstep: each recorded state goes through every shield in turn.

    A slow spell of the machine (another tenant, a frequency change) then lands on all of them alike, so their
    ratio holds where two back-to-back replays of a few seconds each drift apart by tens of per cent.
    """
    acc = {name: ([], [], []) for name in shields}
    for rep in range(repeats + 1):
        for sh in shields.values():
            sh.reset()
        for pos, vel, r_wb, cmd, depth, vid in states:
            for name, sh in shields.items():
                out = sh.filter(cmd, pos, vel, depth=depth, R_wb=r_wb, ids=vid)
                if rep == 0:
                    continue  # warm-up pass
                solve, total, active = acc[name]
                active.append(bool(out.active[0]))
                total.append(out.total_us[0])
                if out.active[0]:
                    solve.append(out.solve_us[0])
    return {name: tuple(np.array(x) for x in v) for name, v in acc.items()}


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
        solve, total, active = replay(HOCBFShield(ShieldConfig(solver=solver), cam), states, args.repeats)
        row = {"solver": solver, **_stats(solve), "active_fraction": round(float(np.mean(active)), 4)}
        per_solver.append(row)
        if whole is None:
            whole = {"solver": solver, **_stats(total)}
        if not args.json:
            print(row)
    formulations = {}
    shields = {
        "default": HOCBFShield(ShieldConfig(), cam),
        "paper": HOCBFShield(ShieldConfig(**PAPER_FORMULATION), cam),
        "backup": HOCBFShield(ShieldConfig(barrier="backup"), cam),  # the option of docs/shield.md, "Backup barrier"
        "no_map": HOCBFShield(ShieldConfig(map_seconds=0.0), cam),  # the default without its local map ("Local map")
        # the setting for a noisy sensor of docs/shield.md, "Depth noise": the median pre-filter and a 3 m local map
        "noisy_sensor": HOCBFShield(ShieldConfig(depth_filter="median_cross", map_radius=3.0), cam),
    }
    for name, (solve, total, active) in replay_interleaved(shields, states, args.repeats).items():
        formulations[name] = {"qp": _stats(solve), "whole_step": _stats(total),
                              "active_fraction": round(float(np.mean(active)), 4)}  # fmt: skip
    formulations["whole_step_mean_ratio"] = round(
        formulations["default"]["whole_step"]["mean_us"] / formulations["paper"]["whole_step"]["mean_us"], 3
    )
    formulations["map_whole_step_mean_ratio"] = round(
        formulations["default"]["whole_step"]["mean_us"] / formulations["no_map"]["whole_step"]["mean_us"], 3
    )
    formulations["noisy_sensor_whole_step_mean_ratio"] = round(
        formulations["noisy_sensor"]["whole_step"]["mean_us"] / formulations["default"]["whole_step"]["mean_us"], 3
    )
    # Point cloud + selection alone (no QP), over the same states.
    shield = HOCBFShield(ShieldConfig(), cam)
    sel = []
    for rep in range(2):
        for pos, vel, r_wb, cmd, depth, _ in states:
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
        "formulations": formulations,
        "paper": PAPER,
        "goal": {"qp_mean_us": 30, "qp_p99_us": 100, "whole_step_mean_us": 100},
        **machine(),
    }
    emit(result, args.json)
    return result
