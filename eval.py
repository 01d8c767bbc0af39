"""Evaluate policies and baselines on the paper's scenes: ``python eval.py [--config configs/eval/<name>.yaml] ...``.

Thin entry point: argument parsing only; the harness is :mod:`shield_nav.evaluation` (see docs/evaluation.md).
With no arguments it runs ``configs/eval/default.yaml`` (a short ablation subset) and prints the table.
"""

from __future__ import annotations

import argparse
import os
import sys

from shield_nav.openmp import limit_spinning

limit_spinning()  # before torch and numba load libgomp (shield_nav/openmp.py)

DEFAULT_CONFIG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "configs", "eval", "default.yaml")


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface (DESIGN.md)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=DEFAULT_CONFIG, help="eval config YAML (default: configs/eval/default.yaml)")
    p.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        metavar="NAME=PATH",
        help="policy checkpoint (exported policy.onnx/.pt or its folder); repeatable",
    )
    p.add_argument("--speeds", help="comma-separated target speeds, e.g. 3,5,7,9")
    p.add_argument("--trials", type=int, help="trials per (configuration, scene, speed)")
    p.add_argument("--scenes", help="FAMILY or FAMILY:INDICES (e.g. ablation:0,3 or benchmark:0-5)")
    p.add_argument("--configurations", help="comma-separated rows (e.g. full,oracle,reactive)")
    p.add_argument("--workers", type=int, help="parallel worker processes")
    p.add_argument("--out", help="output folder (default eval_out/<config name>); re-running resumes it")
    p.add_argument("--seed", type=int, help="trial sampling seed")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="dotted eval-config override")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--video",
        action="store_true",
        help="after the run, re-fly trial 0 of the first scene at the top speed per configuration and record it "
        "(MuJoCo chase view + depth inset as MP4; animated top-down plot if MuJoCo cannot render here)",
    )
    return p


def _pin_arithmetic() -> None:
    """Start this command again with OpenBLAS's and numpy's kernels pinned (``network: fixed_order``).

    numpy and OpenBLAS have loaded by now and read ``OPENBLAS_CORETYPE`` and ``NPY_DISABLE_CPU_FEATURES`` only when
    they load, so the pinned run is a new process with the same arguments (the worker processes inherit it;
    :func:`shield_nav.provenance.pinned_arithmetic_environment`).
    """
    from shield_nav.provenance import pinned_arithmetic_environment

    env = pinned_arithmetic_environment()
    if env is None:
        return
    print(f"eval.py: network fixed_order: restarting with OPENBLAS_CORETYPE={env['OPENBLAS_CORETYPE']} "
          f"NPY_DISABLE_CPU_FEATURES=\"{env.get('NPY_DISABLE_CPU_FEATURES', '')}\" (OpenBLAS's SSE3 kernels and "
          "numpy's baseline loops on every x86-64 processor)", file=sys.stderr, flush=True)  # fmt: skip
    os.execve(sys.executable, [sys.executable, *sys.argv], env)


def main(argv: list[str] | None = None) -> int:
    """Parse, build the config, run, print the table. Bad input exits with status 2 and one clear line."""
    args = build_parser().parse_args(argv)
    if args.video:
        os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen rendering without a display; set before mujoco loads
    from shield_nav.evaluation import ConfigError, EvalError, config_from_args, evaluate

    try:
        cfg, explicit = config_from_args(args)
        if cfg.network == "fixed_order" and argv is None:
            _pin_arithmetic()  # returns only where the kernels are pinned already (or off x86-64)
        out = args.out or os.path.join("eval_out", cfg.name)
        summary = evaluate(cfg, out, explicit, progress=not args.no_progress, argv=sys.argv)
    except (EvalError, ConfigError) as err:
        print(f"eval.py: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print()
    print("\n".join(summary["header"]))
    print()
    print(summary["paper_table"])
    print(f"\nwritten to {out}/ (table.md, table.csv, table.tex, trials.json, outcomes.csv.gz, summary.json, figures/)")
    if args.video:
        from shield_nav.evaluation import prepare, record_videos

        record_videos(prepare(cfg, explicit), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
