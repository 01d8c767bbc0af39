"""Per-trial metrics and their aggregation, with Wilson intervals."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# The circling rule, shared with the training env's ``episode/circling`` (envs/navigation/config.py).
from envs.navigation.config import CIRCLE_TURNS, CIRCLE_WINDOW_S
from shield_nav.evaluation.config import Z95


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for k successes in n trials (``scipy.stats.binomtest(k, n).proportion_ci``).

    p = k/n, c = (p + z^2/(2n)) / (1 + z^2/n), h = z / (1 + z^2/n) * sqrt(p(1-p)/n + z^2/(4n^2));
    the interval is [c - h, c + h] (never outside [0, 1]), at confidence 2 Phi(z) - 1. n = 0 gives (0, 1).
    """
    if n <= 0:
        return 0.0, 1.0
    from scipy.stats import binomtest, norm

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=2.0 * float(norm.cdf(z)) - 1.0, method="wilson")
    # At k = 0 (k = n) the lower (upper) bound is exactly 0 (1); set it so round-off cannot leave 3e-17.
    lo = 0.0 if k == 0 else max(0.0, float(ci.low))
    hi = 1.0 if k == n else min(1.0, float(ci.high))
    return lo, hi


def trajectory_metrics(
    pos: np.ndarray,
    speed: np.ndarray,
    esdf: np.ndarray,
    phi_start: float,
    phi_end: float,
    top: float = float("inf"),
    radius: float = 0.0,
) -> dict[str, float]:
    """Per-trial geometry of one trajectory.

    Inputs: positions (T+1, 3) (start included), speeds |v| (T,) after each step, the ESDF (T+1,) at those
    positions, the height of the scene's obstacles ``top`` and the vehicle's collision radius.

    path_length = sum_t |p_{t+1} - p_t|; mean_speed = mean_t |v_t|; clearance_mean/min = mean/min of the ESDF;
    path_ratio = path_length / (Phi(start) - Phi(end)) (Phi: geodesic distance to the goal region; NaN when the
    trajectory made no geodesic progress); flew_over = 1.0 when the vehicle's sphere cleared the obstacles' top at
    some point (max z > top + radius: in the 1 m above the obstacles that the volume allows, it could pass over
    any of them), else 0.0.
    """
    steps = np.diff(pos, axis=0)
    length = float(np.linalg.norm(steps, axis=1).sum())
    progress = phi_start - phi_end
    return {
        "path_length": length,
        "mean_speed": float(np.mean(speed)) if len(speed) else 0.0,
        "clearance_mean": float(np.mean(esdf)),
        "clearance_min": float(np.min(esdf)),
        "geodesic_progress": float(progress),
        "path_ratio": float(length / progress) if progress > 1e-6 else float("nan"),
        "flew_over": float(np.max(pos[:, 2]) > top + radius),
    }


def _nanmean(values: list[float]) -> float:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    return float(v.mean()) if len(v) else float("nan")


def _circled(turns: float | None) -> float | None:
    """1.0 / 0.0 whether ``max_turns`` reaches :data:`CIRCLE_TURNS`; None where the trial lacks it or it is NaN."""
    if turns is None or not math.isfinite(turns):
        return None
    return float(turns >= CIRCLE_TURNS)


def aggregate(trials: list[dict]) -> dict[str, Any]:
    """Cell metrics over trials (see the module docstring). Shield rates pool control steps over trials."""
    n = len(trials)
    outcomes = [t["outcome"] for t in trials]
    k = outcomes.count("success")
    lo, hi = wilson_interval(k, n)
    succ = [t for t in trials if t["outcome"] == "success"]
    sh = [t["shield"] for t in trials if t.get("shield")]
    steps = sum(s["steps"] for s in sh)
    active = sum(s["active_steps"] for s in sh)
    out: dict[str, Any] = {
        "n": n,
        "successes": k,
        "success_rate": k / n if n else float("nan"),
        "sr_lo": lo,
        "sr_hi": hi,
        "collision_rate": outcomes.count("collision") / n if n else float("nan"),
        "timeout_rate": outcomes.count("timeout") / n if n else float("nan"),
        "oob_rate": outcomes.count("out_of_bounds") / n if n else float("nan"),
        "vel": _nanmean([t["metrics"]["mean_speed"] for t in succ]),
        "clearance_mean": _nanmean([t["metrics"]["clearance_mean"] for t in trials]),
        "clearance_min": float(np.min([t["metrics"]["clearance_min"] for t in trials])) if n else float("nan"),
        "path_ratio": _nanmean([t["metrics"]["path_ratio"] for t in succ]),
        # Successes that flew over the obstacles (NaN for trial files written before the metric existed).
        "over_top": _nanmean([t["metrics"].get("flew_over") for t in succ]),
        # Flights that circled: net heading rotation >= CIRCLE_TURNS within CIRCLE_WINDOW_S (NaN without the metric).
        "circling": _nanmean([_circled(t["metrics"].get("max_turns")) for t in trials]),
    }
    if sh:
        out.update(
            {
                "shield_active": active / steps if steps else 0.0,
                "corr_mean": sum(s["corr_sum"] for s in sh) / active if active else 0.0,
                "corr_max": max(s["corr_max"] for s in sh),
                "relaxed": sum(s["relaxed_steps"] for s in sh) / steps if steps else 0.0,
                "qp_us_mean": sum(s["solve_us_sum"] for s in sh) / active if active else 0.0,
                "qp_us_max": max(s["solve_us_max"] for s in sh),
                "shield_us_mean": sum(s["total_us_sum"] for s in sh) / steps if steps else 0.0,
                # Steps flown on another of the policy's candidates (shield.hypotheses; 0 for older trial files).
                "switched": sum(s.get("switched_steps", 0) for s in sh) / steps if steps else 0.0,
            }
        )
    return out


def max_turns(traj: np.ndarray, times: np.ndarray, window_s: float = CIRCLE_WINDOW_S) -> float | None:
    """The largest net rotation [full turns] of a flight's heading across ``window_s`` of it.

    ``traj`` is ``(T, >= 5)`` (x, y, z, speed, heading [rad]), ``times`` its points' times [s]. The heading is
    unwrapped (each change between recorded points taken in (-pi, pi]: at a point every 0.1 s that holds below
    1,800 deg/s) and every point's is compared with the last point's at most ``window_s`` later (a point within
    ``window_s`` of the flight's end: with the end). Turning left then right cancels; orbiting adds up. ``None``
    for fewer than two points or without the heading column.
    """
    tr, t = np.asarray(traj, dtype=np.float64), np.asarray(times, dtype=np.float64)
    if tr.ndim != 2 or t.shape != (len(tr),):
        raise ValueError(f"need a trajectory (T, C) with T times, got shapes {tr.shape} and {t.shape}")
    if not (math.isfinite(window_s) and window_s > 0):
        raise ValueError(f"window_s must be finite and > 0, got {window_s}")
    if tr.shape[1] < 5 or len(tr) < 2:
        return None
    if not np.all(np.isfinite(tr[:, 4])):
        raise ValueError("the heading column holds a non-finite value")
    dh = (np.diff(tr[:, 4]) + np.pi) % (2.0 * np.pi) - np.pi
    h = np.concatenate(([0.0], np.cumsum(dh)))
    j = np.searchsorted(t, t + window_s + 1e-9, side="right") - 1  # the last point within the window
    return float(np.max(np.abs(h[j] - h)) / (2.0 * np.pi))
