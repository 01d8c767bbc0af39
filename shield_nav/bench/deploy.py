"""Cost of one control step of the deployed Full system: ``python -m shield_nav.bench deploy --json``.

Flies ``eval.py``'s pinned trial 0 of a few scenes through :class:`shield_nav.deploy.ShieldedPilot` (the exported
policy through onnxruntime behind the default shield, one vehicle, the simulator only rendering the image and flying
the commands) and times every :meth:`~shield_nav.deploy.ShieldedPilot.step`: the whole step (state vector, network,
action mapping, shield), the network and the shield alone. Reported per flight and over all of them: mean, p50,
p99 and max [us], the share of steps with the shield acting, and the share of steps over the 10 ms control period.
Default flights: a geometric benchmark scene at 3 m/s, a Perlin field at 5 m/s, a dense ablation scene at 9 m/s.
Also reported: ``warm_up_s``, what :meth:`~shield_nav.deploy.ShieldedPilot.warm_up` took (``load`` runs it: with
numba's on-disk cache empty it compiles the kernels, seconds; with it filled, a fraction of a second), and
``first_step_us``, the first control step after it, the step a vehicle's first period holds.
``--handover`` adds the stall handover of ``eval.py``'s ``full_handover`` row (its camera map is kept from the first
step of every flight; ``handed_steps`` says how many steps the planner flew). ``--real-time`` starts each step one
control period after the last, as a vehicle's loop does, rather than as soon as the simulator is done: with
``--replan-delay`` the planning thread then has the periods' idle time, as on a vehicle (back to back a handed step
waits for a plan that a paced loop has had time to finish).
"""

from __future__ import annotations

import numpy as np

from shield_nav.bench.common import emit, machine, parser

FLIGHTS = ("benchmark:3:3", "benchmark:13:5", "ablation:7:9")


def _stats(us: np.ndarray) -> dict:
    return {"mean": round(float(us.mean()), 1), "p50": round(float(np.percentile(us, 50)), 1),
            "p99": round(float(np.percentile(us, 99)), 1), "max": round(float(us.max()), 1)}  # fmt: skip


def main(argv: list[str]) -> dict:
    """Fly the flights and time the pilot's steps."""
    p = parser("deploy", __doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full", help="policy folder or file")
    p.add_argument("--flights", default=",".join(FLIGHTS), help="comma-separated family:scene:speed")
    p.add_argument("--handover", action="store_true", help="with the stall handover (the full_handover row's rules)")
    p.add_argument("--replan-delay", type=int, default=0, metavar="L",
                   help="with --handover: plans on a thread, flown L steps later (default 0)")  # fmt: skip
    p.add_argument("--real-time", action="store_true",
                   help="start each step one control period after the last, as on a vehicle (default: as soon as the "
                        "simulator is done)")  # fmt: skip
    args = p.parse_args(argv)
    flights = []
    for item in args.flights.split(","):
        parts = item.split(":")
        try:
            family, scene, speed = parts[0], int(parts[1]), float(parts[2])
        except (IndexError, ValueError):
            p.error(f"--flights: {item!r} is not family:scene:speed")
        flights.append((family, scene, speed))
    from shield_nav.deploy import ShieldedPilot, fly_trial

    if args.replan_delay and not args.handover:
        p.error("--replan-delay delays the handover planner's plans; it needs --handover")
    pilot = ShieldedPilot.load(args.checkpoint, handover=args.handover, replan_delay=args.replan_delay, warm_up=False)
    warm_up_s = pilot.warm_up()  # what load() does: every kernel's first call (compiled, or read from numba's cache)
    first = fly_trial(pilot, *flights[0])  # a flight first: onnxruntime's and the allocator's steady state
    result: dict = {"benchmark": "deploy", "checkpoint": args.checkpoint, "runtime": pilot.policy.info.kind,
                    "handover": bool(args.handover), "replan_delay": args.replan_delay,
                    "real_time": bool(args.real_time),
                    "warm_up_s": round(warm_up_s, 3),
                    "first_step_us": round(float(first["step_us"][0]), 1), "flights": []}  # fmt: skip
    period_us = 1e6 * pilot.shield.cfg.control_dt if pilot.shield is not None else 1e4
    all_step, all_policy, all_shield = [], [], []
    for family, scene, speed in flights:
        r = fly_trial(pilot, family, scene, speed, real_time=args.real_time)
        rec = {"flight": f"{family}:{scene}:{speed:g}", "outcome": r["outcome"], "steps": r["steps"],
               "shield_active": round(r["shield_active"], 4), "step_us": _stats(r["step_us"]),
               "policy_us": _stats(r["policy_us"]), "shield_us": _stats(r["shield_us"]),
               "handed_steps": r["handed_steps"]}  # fmt: skip
        result["flights"].append(rec)
        all_step.append(r["step_us"])
        all_policy.append(r["policy_us"])
        all_shield.append(r["shield_us"])
        print(f"{rec['flight']}: {r['outcome']}, {r['steps']} steps, whole step {rec['step_us']['mean']:.0f} us mean / "
              f"{rec['step_us']['p99']:.0f} us p99 (policy {rec['policy_us']['mean']:.0f}, shield "
              f"{rec['shield_us']['mean']:.0f} us mean), shield acting on {100 * r['shield_active']:.1f} %",
              flush=True)  # fmt: skip
    step = np.concatenate(all_step)
    result["step_us"] = _stats(step)
    result["policy_us"] = _stats(np.concatenate(all_policy))
    result["shield_us"] = _stats(np.concatenate(all_shield))
    result["steps_over_period"] = round(float(np.mean(step > period_us)), 6)
    pilot.close()
    result.update(machine())
    emit(result, args.json)
    return result
