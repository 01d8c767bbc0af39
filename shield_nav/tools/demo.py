"""Vehicle demo: hover and attitude steps on the simulated quadrotor, printing the tracking figures.

``python -m shield_nav.tools.demo [--plot PATH]``. Runs in a few seconds; the same experiments back the vehicle tests
and docs/vehicle.md.
"""

from __future__ import annotations

import argparse

from envs.vehicle.config import VehicleConfig
from envs.vehicle.response import attitude_step, hover_hold, tilt_acceleration


def main(argv: list[str] | None = None) -> None:
    """Fly the experiments and print a table; optionally save a step-response figure."""
    p = argparse.ArgumentParser(prog="python -m shield_nav.tools.demo", description=__doc__.splitlines()[0])
    p.add_argument("--plot", default=None, help="save a step-response figure (PNG) to this path")
    args = p.parse_args(argv)
    cfg = VehicleConfig()
    print(
        f"Vehicle: {cfg.airframe.mass} kg, thrust/weight {cfg.motor.thrust_to_weight}, "
        f"inner loop {1 / cfg.physics_dt:.0f} Hz, commands {1 / cfg.command_dt:.0f} Hz"
    )
    h = hover_hold()
    print(
        f"hover 5 s after a 0.5 rad/s kick: max altitude error {100 * h['max_altitude_error_m']:.1f} cm, "
        f"final tilt {h['final_tilt_deg']:.3f} deg, xy drift {100 * h['xy_drift_m']:.1f} cm"
    )
    print(
        f"{'step':<12}{'rise 10-90% [s]':>17}{'overshoot [%]':>15}{'settle 2% [s]':>15}{'final [deg]':>13}"
        f"{'cross-axis [deg]':>18}"
    )
    steps = {}
    for axis, amp, dur in (("roll", 20.0, 1.5), ("pitch", 20.0, 1.5), ("roll", 45.0, 1.5), ("yaw", 45.0, 2.5)):
        r = attitude_step(axis, amp, dur, cfg)
        steps[f"{axis} {amp:g} deg"] = r
        print(
            f"{axis + f' {amp:g} deg':<12}{r.rise_time:>17.3f}{r.overshoot_pct:>15.2f}{r.settling_time:>15.3f}"
            f"{r.final:>13.2f}{r.max_cross_axis:>18.3f}"
        )
    for tilt in (15.0, 30.0):
        a = tilt_acceleration(tilt, 2.0, cfg)
        print(
            f"level flight at {tilt:g} deg pitch, {a['speed_m_s']:.2f} m/s: forward accel "
            f"{a['accel_measured'][0]:.3f} m/s^2 (model g tan - drag: {a['accel_predicted'][0]:.3f}, "
            f"g tan alone: {a['accel_no_drag']:.3f})"
        )
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 3.6))
        for name, r in steps.items():
            ax.plot(r.t, r.y / r.target, label=name)
        ax.axhline(1.0, color="k", lw=0.6, ls="--")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("attitude / reference")
        ax.set_title("PX4-style inner loop: attitude step responses")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
        print(f"saved {args.plot}")


if __name__ == "__main__":
    main()
