"""How fast could this vehicle fly the routes that were flown? A ceiling for the realised speed of an evaluation.

``python -m shield_nav.tools.speed_bound <eval_out> [<eval_out> ...] [--rows expert] [--speeds 7] [--accel 11.7]
[--lag 0.154] [--json] [--plot PNG]``

reads the successful trials of an ``eval.py`` output folder (their recorded trajectories, one point every
``trajectory_every`` control steps) and asks, for each, how fast a vehicle at the limits of this airframe could
have flown the same curve in space: the same route and the same bends, any speed along it. The answer is the
minimum-time speed profile along the flown path (:func:`time_optimal_profile`) under

* the target speed as a speed limit (the task asks for it; the realised-speed bar of the high-speed issue is a share
  of it),
* a horizontal acceleration of at most ``--accel`` in all, along and across the path together (a friction circle):
  by default ``g tan(50 deg)`` = 11.7 m/s^2, what the vehicle's 50 deg tilt clamp gives in level flight,
* a start from hover that can accelerate only after the attitude loop's lag ``--lag`` (its first-order time
  constant, 0.154 s; docs/vehicle.md).

The mean speed of that profile, ``path length / minimum time``, is the highest ``mean_speed`` any tracker could
realise on that route. Per row and speed it reports the realised speed of the successes, that ceiling (``bound``),
and the ceiling of a straight route of the same length (``straight``: what the start from hover alone allows), all
as shares of the target speed, and the share of successes whose ceiling is below ``--bar`` (default 0.85). So the
gap between target and realised speed splits into the start (``1 - straight``), the route's bends (``straight -
bound``) and the tracker (``bound - realised``). A vehicle that climbs while it turns can briefly exceed the
level-flight acceleration, and a different route (less clearance, fewer bends) could be faster: the ceiling is the
route's, not the scene's.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys
from typing import Any

import numpy as np

from shield_nav.algorithms.expert_paths import windowed_curvature

RESAMPLE_DS = 0.25
"""Spacing [m] at which a flown path is resampled by arc length before its curvature is measured."""
CURVATURE_WINDOW = 4
"""Resampled segments on either side over which the turning angle is measured (1 m at the default spacing): the
recorded points are 0.1 s apart, so the polyline's corners are spread over the window, as the vehicle flew them."""
DEFAULT_ACCEL = 9.81 * math.tan(math.radians(50.0))
"""Level-flight horizontal acceleration at the vehicle's 50 deg tilt clamp [m/s^2]."""
DEFAULT_LAG = 1.0 / 6.5
"""The attitude loop's time constant [s] (``K_p`` 6.5 /s, docs/vehicle.md)."""


def time_optimal_profile(kappa: np.ndarray, ds: float, v_max: float, accel: float,
                         v0: float = 0.0) -> np.ndarray:  # fmt: skip
    """Fastest speeds (K+1,) at the samples of a path with curvature ``kappa`` (K+1,) and spacing ``ds``.

    The speed is capped by ``v_max`` and by the bends, ``v^2 kappa <= accel``, and the acceleration along the path
    by what the bend leaves of ``accel``: ``|dv^2/ds| / 2 <= sqrt(accel^2 - (v^2 kappa)^2)``. A forward pass from
    ``v0`` accelerates as hard as that allows; a backward pass brakes into every later cap in time.
    """
    kappa = np.abs(np.asarray(kappa, dtype=np.float64))
    if kappa.ndim != 1 or len(kappa) < 2:
        raise ValueError(f"need curvatures at two or more samples, got shape {kappa.shape}")
    if not (ds > 0 and v_max > 0 and accel > 0 and v0 >= 0):
        raise ValueError(f"need ds, v_max, accel > 0 and v0 >= 0, got {ds}, {v_max}, {accel}, {v0}")
    cap = np.minimum(v_max, np.sqrt(accel / np.maximum(kappa, 1e-12)))
    v = np.empty_like(cap)
    v[0] = min(v0, cap[0])
    for k in range(len(v) - 1):
        along = math.sqrt(max(accel**2 - (v[k] ** 2 * kappa[k]) ** 2, 0.0))
        v[k + 1] = min(cap[k + 1], math.sqrt(v[k] ** 2 + 2.0 * along * ds))
    for k in range(len(v) - 2, -1, -1):
        along = math.sqrt(max(accel**2 - (v[k + 1] ** 2 * kappa[k + 1]) ** 2, 0.0))
        v[k] = min(v[k], math.sqrt(v[k + 1] ** 2 + 2.0 * along * ds))
    return v


def profile_time(v: np.ndarray, ds: float) -> float:
    """Time [s] to fly a profile ``v`` (K+1,) of spacing ``ds``, at constant acceleration between samples."""
    mean = 0.5 * (v[:-1] + v[1:])
    if np.any(mean <= 0):
        raise ValueError("the profile stands still on a segment: no finite time")
    return float(np.sum(ds / mean))


def resample(points: np.ndarray, ds: float) -> np.ndarray:
    """Points (M, 3) of a polyline resampled every ``ds`` of arc length (the end included); repeated points dropped."""
    p = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    keep = np.concatenate(([True], seg > 1e-9))
    p = p[keep]
    s = np.concatenate(([0.0], np.cumsum(seg[seg > 1e-9])))
    if len(p) < 2:
        raise ValueError("the path has no length")
    n = max(int(math.ceil(s[-1] / ds)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(t, s, p[:, i]) for i in range(3)], axis=1)


def flight_ceiling(points: np.ndarray, v_max: float, accel: float, lag: float,
                   ds: float = RESAMPLE_DS, window: int = CURVATURE_WINDOW) -> dict[str, float]:  # fmt: skip
    """The ceiling of one flown path (M, 3): ``length`` [m], ``bound`` and ``straight`` mean speeds [m/s].

    ``bound`` is the length over the minimum time along the path's own bends (plus ``lag`` before the vehicle can
    accelerate); ``straight`` the same along a straight line of that length.
    """
    pts = resample(points, ds)
    step = float(np.linalg.norm(pts[1] - pts[0]))
    length = step * (len(pts) - 1)
    kappa = windowed_curvature(pts[None], window)[0]
    t_bend = profile_time(time_optimal_profile(kappa, step, v_max, accel), step) + lag
    t_line = profile_time(time_optimal_profile(np.zeros_like(kappa), step, v_max, accel), step) + lag
    return {"length": length, "bound": length / t_bend, "straight": length / t_line}


def ceilings(
    out_dir: str,
    rows: list[str] | None = None,
    speeds: list[float] | None = None,
    accel: float = DEFAULT_ACCEL,
    lag: float = DEFAULT_LAG,
    bar: float = 0.85,
) -> list[dict[str, Any]]:
    """Per (row, speed) of an eval folder: successes, realised speed and the ceilings, as shares of the target."""
    files = sorted(glob.glob(os.path.join(out_dir, "units", "*.json")))
    if not files:
        raise FileNotFoundError(f"no unit files under {os.path.join(out_dir, 'units')!r}: not an eval.py output")
    groups: dict[tuple[str, float], list[tuple[float, dict[str, float]]]] = {}
    for path in files:
        with open(path) as fh:
            unit = json.load(fh)
        speed = float(unit["speed"])
        if (rows and unit["row"] not in rows) or (speeds and speed not in speeds):
            continue
        entry = groups.setdefault((unit["row"], speed), [])
        for t in unit["trials"]:
            if t["outcome"] != "success":
                continue
            if not t.get("traj"):
                raise ValueError(f"{path}: trial {t.get('trial')} has no trajectory (trajectory_every too large?)")
            ceiling = flight_ceiling(np.asarray(t["traj"], dtype=np.float64)[:, :3], speed, accel, lag)
            entry.append((float(t["metrics"]["mean_speed"]), ceiling))
    if not groups:
        raise ValueError(f"no unit of {out_dir!r} matches rows {rows} and speeds {speeds}")
    out = []
    for (row, speed), flights in sorted(groups.items()):
        n = len(flights)
        realised = np.array([f[0] for f in flights]) / speed
        bound = np.array([f[1]["bound"] for f in flights]) / speed
        straight = np.array([f[1]["straight"] for f in flights]) / speed

        def mean(x: np.ndarray) -> float | None:
            return float(x.mean()) if len(x) else None

        below = mean((bound < bar).astype(float))
        out.append({"row": row, "speed": speed, "successes": n, "realised": mean(realised), "bound": mean(bound),
                    "straight": mean(straight), "below_bar": below, "bar": bar})  # fmt: skip
    return out


def plot(result: list[dict[str, Any]], path: str, title: str = "") -> None:
    """Per row, realised speed, the route's ceiling and the start-only ceiling against the target speed (x target)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted({r["row"] for r in result})
    fig, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 3.4), squeeze=False, sharey=True)
    for ax, row in zip(axes[0], rows, strict=True):
        pts = sorted((r for r in result if r["row"] == row and r["successes"]), key=lambda r: r["speed"])
        v = [r["speed"] for r in pts]
        ax.plot(v, [r["straight"] for r in pts], "o:", color="0.5", label="straight route (start from hover)")
        ax.plot(v, [r["bound"] for r in pts], "s--", color="tab:blue", label="ceiling on the flown routes")
        ax.plot(v, [r["realised"] for r in pts], "o-", color="tab:red", label="realised (successes)")
        ax.axhline(pts[0]["bar"] if pts else 0.85, color="k", lw=0.8, alpha=0.5)
        ax.set_title(row)
        ax.set_xlabel("target speed [m/s]")
        ax.set_xticks(v)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("mean speed / target")
    axes[0][-1].legend(loc="lower left", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Command line (module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.speed_bound", description=__doc__.split("\n")[0])
    ap.add_argument(
        "out_dirs",
        nargs="+",
        metavar="out_dir",
        help="eval.py output folders (their rows are reported together; a row and speed twice is refused)",
    )
    ap.add_argument("--rows", default=None, help="comma-separated rows (default: all)")
    ap.add_argument("--speeds", default=None, help="comma-separated target speeds (default: all)")
    ap.add_argument(
        "--accel",
        type=float,
        default=DEFAULT_ACCEL,
        help=f"horizontal acceleration limit [m/s^2] (default {DEFAULT_ACCEL:.2f}, g tan 50 deg)",
    )
    ap.add_argument(
        "--lag",
        type=float,
        default=DEFAULT_LAG,
        help=f"delay before the start's acceleration [s] (default {DEFAULT_LAG:.3f})",
    )
    ap.add_argument("--bar", type=float, default=0.85, help="realised speed bar, share of the target (default 0.85)")
    ap.add_argument("--json", action="store_true", help="one JSON line per row and speed instead of a table")
    ap.add_argument("--plot", default=None, metavar="PNG", help="also draw the shares against the target speed")
    args = ap.parse_args(argv)
    if not args.accel > 0 or not math.isfinite(args.accel):
        ap.error(f"--accel must be a finite number > 0, got {args.accel}")
    if not args.lag >= 0 or not math.isfinite(args.lag):
        ap.error(f"--lag must be a finite number >= 0, got {args.lag}")
    rows = args.rows.split(",") if args.rows else None
    try:
        speeds = [float(s) for s in args.speeds.split(",")] if args.speeds else None
    except ValueError:
        ap.error(f"--speeds takes comma-separated numbers, got {args.speeds!r}")
    result: list[dict[str, Any]] = []
    try:
        for out_dir in args.out_dirs:
            for r in ceilings(out_dir, rows, speeds, args.accel, args.lag, args.bar):
                if any((q["row"], q["speed"]) == (r["row"], r["speed"]) for q in result):
                    raise ValueError(f"row {r['row']!r} at {r['speed']:g} m/s is in more than one folder ({out_dir!r})")
                result.append(r)
    except (FileNotFoundError, ValueError) as exc:
        print(f"speed_bound: {exc}", file=sys.stderr)
        return 2
    if args.plot:
        plot(result, args.plot, title=", ".join(os.path.basename(os.path.normpath(d)) for d in args.out_dirs))
    if args.json:
        for r in result:
            print(json.dumps(r))
        return 0

    def fmt(x: float | None) -> str:
        return "-" if x is None else f"{x:.3f}"

    print(f"| row | speed | successes | realised | bound (route, at {args.accel:.1f} m/s^2) | straight (start only) "
          f"| bound < {args.bar:g} |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in result:
        print(f"| {r['row']} | {r['speed']:g} | {r['successes']} | {fmt(r['realised'])} | {fmt(r['bound'])} "
              f"| {fmt(r['straight'])} | {fmt(r['below_bar'])} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
