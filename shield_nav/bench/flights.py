"""An evaluation's throughput, and where its time goes: ``python -m shield_nav.bench flights [--json]``.

Flies a small, fixed evaluation in this process (one worker; by default the shipped Full behind the shield at 5 m/s
on two ablation validation scenes, 25 trials each: one batch of 25 per scene, as Table I flies them) and reports the
wall clock, the vehicle-steps flown and their rate. ``--profile`` runs it under cProfile and adds each part's share
of the flight time (the profiler slows the Python-heavy parts more than the compiled ones, so read the shares as
where to look, the wall clock without ``--profile`` as the speed). Keys: ``flights``, ``vehicle_steps``,
``seconds``, ``vehicle_steps_per_s``, ``flights_per_min``, with ``--profile`` ``shares`` (of the flights' time:
``env_step``, ``vehicle``, ``observations``, ``rendering``, ``shield``, ``shield_selection``, ``shield_qp``,
``network``).

The arithmetic is the process's: ``eval.py`` pins OpenBLAS's and numpy's kernels for ``network: fixed_order``, this
benchmark does not (the flights are the same kind of work either way).
"""

from __future__ import annotations

import json
import os
import tempfile
import time

from shield_nav.bench.common import emit, machine, parser

# The functions whose cumulative time makes each share (module path suffix, function name).
_PARTS = {
    "flights": [("evaluation/rollout.py", "_run_batch")],
    "env_step": [("navigation/env.py", "step")],
    "vehicle": [("vehicle/vehicles.py", "step")],
    "observations": [("navigation/env.py", "_get_observations")],
    "rendering": [("camera/renderer.py", "render")],
    "shield": [("safety/shield.py", "filter_env")],
    "shield_selection": [("safety/shield.py", "constraints")],
    "shield_qp": [("safety/shield.py", "solve")],
    "network": [("evaluation/policies.py", "step")],
}


def _shares(stats: dict) -> dict[str, float]:
    """Each part's cumulative time over the flights' (``_run_batch``) from a cProfile ``stats`` table."""
    cum: dict[str, float] = {}
    for part, names in _PARTS.items():
        cum[part] = sum(v[3] for (file, _, func), v in stats.items()
                        for suffix, name in names if func == name and file.endswith(suffix))  # fmt: skip
    total = cum.pop("flights")
    if total <= 0:
        raise RuntimeError("the profile holds no flight (_run_batch): nothing was flown")
    return {part: round(t / total, 3) for part, t in cum.items()}


def main(argv: list[str]) -> dict:
    """Fly the evaluation, time it, optionally profile it."""
    p = parser("flights", __doc__.splitlines()[0])
    p.add_argument("--config", default="configs/eval/validation_ablation.yaml", help="an eval config")
    p.add_argument("--configurations", default="full", help="rows, comma-separated (default: full)")
    p.add_argument("--speed", type=float, default=5.0, help="target speed [m/s] (default 5)")
    p.add_argument("--scenes", default="0,1", help="scene indices of the config's family (default 0,1)")
    p.add_argument("--trials", type=int, default=25, help="trials per scene (default 25: one batch of 25)")
    p.add_argument("--network", default="fixed_order", choices=("fixed_order", "export"), help="the network runtime")
    p.add_argument("--profile", action="store_true", help="fly under cProfile and report each part's share")
    args = p.parse_args(argv)
    if args.trials < 1:
        p.error(f"--trials must be >= 1, got {args.trials}")
    if args.speed <= 0:
        p.error(f"--speed must be > 0, got {args.speed}")
    try:
        scenes = [int(s) for s in args.scenes.split(",") if s.strip()]
    except ValueError:
        p.error(f"--scenes must be comma-separated integers, got {args.scenes!r}")
    from shield_nav.evaluation import ConfigError, EvalError, evaluate, prepare
    from shield_nav.evaluation.config import load_eval_config

    overrides = [f"configurations=[{args.configurations}]", f"speeds=[{args.speed}]", f"scenes.indices={scenes}",
                 f"trials_per_scene={args.trials}", f"batch_size={args.trials}", "workers=1",
                 f"network={args.network}"]  # fmt: skip
    try:  # bad input is named before any flight
        cfg = load_eval_config(args.config, overrides)
        prepare(cfg)
    except (ConfigError, EvalError) as err:
        p.error(str(err))
    with tempfile.TemporaryDirectory(prefix="bench_flights_") as out:
        if args.profile:
            import cProfile
            import pstats

            prof = cProfile.Profile()
            t0 = time.perf_counter()
            prof.runcall(evaluate, cfg, out, progress=False)
            seconds = time.perf_counter() - t0
            shares = _shares(pstats.Stats(prof).stats)  # type: ignore[attr-defined]
        else:
            t0 = time.perf_counter()
            evaluate(cfg, out, progress=False)
            seconds = time.perf_counter() - t0
            shares = None
        with open(os.path.join(out, "trials.json")) as f:
            trials = json.load(f)
    steps = sum(int(t["steps"]) for t in trials)
    result = {"benchmark": "flights", "config": args.config, "configurations": args.configurations,
              "speed": args.speed, "scenes": scenes, "trials_per_scene": args.trials, "network": args.network,
              "flights": len(trials), "vehicle_steps": steps, "seconds": round(seconds, 2),
              "vehicle_steps_per_s": round(steps / seconds, 1),
              "flights_per_min": round(60.0 * len(trials) / seconds, 2), "profiled": args.profile}  # fmt: skip
    if shares is not None:
        result["shares"] = shares
    print(f"{len(trials)} flights, {steps} vehicle-steps in {seconds:.1f} s: {steps / seconds:.0f} vehicle-steps/s"
          + (" (under cProfile)" if args.profile else ""), flush=True)  # fmt: skip
    if shares is not None:
        print("shares of the flights' time: " + ", ".join(f"{k} {v:.0%}" for k, v in shares.items()), flush=True)
    result.update(machine())
    emit(result, args.json)
    return result
