"""The ``train.py`` command line: parse, resolve the config, check its inputs, then train.

Everything up to the first training step's imports is light: the parser, the typed config and the pre-flight checks
(:mod:`~shield_nav.training.checks`) run without importing torch or rsl-rl, so ``--help`` and a bad key, file or
device answer in about 2 s. The runner (:mod:`~shield_nav.training.runner`) is imported only to train.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from envs.config import ConfigError, stored_config
from shield_nav.training.checks import check_files, in_run_folder, read_checkpoint_infos
from shield_nav.training.config import TrainConfig, load_train_config

__all__ = ["build_parser", "config_from_args", "main", "overrides_from_args"]


def build_parser() -> argparse.ArgumentParser:
    """The ``train.py`` argument parser."""
    p = argparse.ArgumentParser(prog="train.py", description="Train the depth CNN+GRU policy with rsl-rl PPO.")
    p.add_argument("--config", help="configs/train/<name>.yaml (required unless --resume)")
    p.add_argument("--set", nargs="+", action="extend", default=[], metavar="A.B=V",
                   help="dotted overrides, e.g. env.num_envs=32 (repeatable; all apply, in order); with a pipeline, "
                        "STAGE:A.B=V applies to that stage only")  # fmt: skip
    p.add_argument("--num-envs", type=int, help="shorthand for --set env.num_envs=N")
    p.add_argument("--max-iterations", type=int, help="total iterations of the run")
    p.add_argument("--seed", type=int, help="sets seed and env.seed")
    p.add_argument("--device", help="cpu | cuda | cuda:i")
    p.add_argument("--log-dir", help="root of the run folders (default: logs)")
    p.add_argument(
        "--resume",
        help="model_<it>.pt to continue (its run folder and stored config are reused), or a "
        "pipeline folder (its finished stages are skipped)",
    )
    return p


def overrides_from_args(args: argparse.Namespace) -> list[str]:
    """``--set`` plus the shorthand flags, as dotted overrides in the order they apply."""
    overrides = list(args.set)
    if args.num_envs is not None:
        overrides.append(f"env.num_envs={args.num_envs}")
    if args.max_iterations is not None:
        overrides.append(f"max_iterations={args.max_iterations}")
    if args.seed is not None:
        overrides += [f"seed={args.seed}", f"env.seed={args.seed}"]
    if args.device is not None:
        overrides.append(f"device={args.device}")
    if args.log_dir is not None:
        overrides.append(f"log_root={args.log_dir}")
    return overrides


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """Resolve the config: (stored config of --resume | --config) + --set + shorthand flags."""
    overrides = overrides_from_args(args)
    for item in overrides:
        if ":" in item.partition("=")[0]:
            raise ConfigError(f"override '{item}': a '<stage>:' prefix applies to a pipeline's stages only "
                              "(--config <pipeline>.yaml or --resume <pipeline folder>)")  # fmt: skip
    if args.resume is not None:
        stored = stored_config(TrainConfig, read_checkpoint_infos(args.resume, "--resume")["config"])
        if args.config is not None:
            print(f"[train] --resume: using the run's stored config; ignoring --config {args.config}", flush=True)
        if not in_run_folder(args.resume) and not any(o.startswith("log_root=") for o in overrides):
            # A packaged policy continues in a new run folder; the log_root it stored is its trainer's machine's.
            default = TrainConfig.log_root
            print(f"[train] --resume: {args.resume} is not in a run folder; continuing in a new one under "
                  f"{default!r} (--log-dir to choose; the stored log_root {stored.get('log_root')!r} was where it "
                  "was trained)", flush=True)  # fmt: skip
            stored = {**stored, "log_root": default}
        # The stored config is what ran; keys given now must exist in its algorithm's section.
        return load_train_config(overrides=overrides, base=load_train_config(overrides=stored))
    if args.config is None:
        raise ConfigError("--config is required (or --resume)")
    cfg = load_train_config(files=args.config, overrides=overrides)
    if getattr(cfg.runner.algorithm, "lr_schedule_iterations", None) == 0:
        # Frozen into the stored config, so a resume that extends --max-iterations keeps the schedule it started.
        cfg.runner.algorithm.lr_schedule_iterations = cfg.max_iterations
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    """``python train.py ...``: parse, resolve the config (failing fast on bad keys), train."""
    from shield_nav.training import pipeline

    args = build_parser().parse_args(argv)
    staged = (args.resume is not None and os.path.isdir(args.resume)) or (
        args.resume is None and args.config is not None and pipeline.is_pipeline_file(args.config)
    )
    if staged:  # a staged recipe: its stages run in sequence (shield_nav/training/pipeline.py)
        try:
            if args.max_iterations is not None:
                raise ConfigError(
                    "--max-iterations: a pipeline's stages set their own; use "
                    "--set max_iterations=N to change every stage, or edit the stage's 'set'"
                )
            overrides = overrides_from_args(args)
            if args.resume is not None:
                root = args.resume
                if args.config is not None:
                    print(f"[pipeline] --resume: using the folder's stored configs; ignoring --config {args.config}",
                          flush=True)  # fmt: skip
                pipeline.load_stored(root, overrides)  # fail on a bad override before any work
            else:
                root = pipeline.start(pipeline.load_pipeline(args.config), overrides)
        except (ConfigError, ValueError) as err:
            print(f"train.py: error: {err}", file=sys.stderr)
            return 2
        print(f"[pipeline] folder: {root}", flush=True)
        pipeline.run(root, overrides)
        return 0
    try:
        cfg = config_from_args(args)
        check_files(cfg, args.resume)
    except (ConfigError, ValueError) as err:
        print(f"train.py: error: {err}", file=sys.stderr)
        return 2
    from shield_nav.training.runner import train  # torch, rsl-rl: only now that the inputs are known to be good

    try:
        train(cfg, resume=args.resume)
    except ConfigError as err:  # an input only readable with torch (e.g. a checkpoint's shapes), before iteration 0
        print(f"train.py: error: {err}", file=sys.stderr)
        return 2
    return 0
