"""Training throughput: a few PPO iterations of the ``dijkstra_cbf`` config, end to end (collection + learning).

Any training config works (``--config configs/experiments/teacher_dijkstra_cbf.yaml`` measures a privileged teacher;
a ``distill_*.yaml`` config needs its teacher checkpoint).

``python -m shield_nav.bench train --json [--num-envs N] [--iterations K] [--warmup W] [--config PATH]``.
Runs rsl-rl's ``OnPolicyRunner`` exactly as ``train.py`` builds it (no log folder), drops ``W`` warm-up iterations
(first-call allocations, numba/oneDNN warm-up), and reports the mean over the remaining ones:
``env_steps_per_s = num_envs * num_steps_per_env / (collect_s + learn_s)``.
"""

from __future__ import annotations

import os
import time
from typing import Any

import torch

from shield_nav.bench.common import emit, machine, parser, peak_rss_mb
from shield_nav.training import (
    REPO_ROOT,
    check_files,
    configure_threads,
    load_train_config,
    make_env,
    make_runner,
)


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; print progress and (with ``--json``) one JSON object last."""
    p = parser("train", __doc__.splitlines()[0])
    p.add_argument("--config", default=os.path.join(REPO_ROOT, "configs", "train", "dijkstra_cbf.yaml"))
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--iterations", type=int, default=3, help="measured iterations")
    p.add_argument("--warmup", type=int, default=1, help="iterations run first and not measured")
    p.add_argument("--set", nargs="*", action="extend", default=[], metavar="A.B=V", help="extra config overrides")
    args = p.parse_args(argv)

    cfg = load_train_config(args.config, overrides=[f"env.num_envs={args.num_envs}", *args.set])
    check_files(cfg)  # a distillation config needs its teacher checkpoint
    threads = configure_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    env = make_env(cfg)
    build_s = time.perf_counter() - t0
    runner = make_runner(env, cfg, log_dir=None, device=cfg.device)
    if cfg.runner.class_name == "DistillationRunner" and cfg.runner.expert.kind:
        runner.alg.teacher_loaded = True  # a scripted expert (train.py does the same): no weights to load
    elif cfg.runner.class_name == "DistillationRunner":
        runner.load(cfg.runner.teacher_checkpoint)
    actor = runner.alg.get_policy()
    critic = getattr(runner.alg, "critic", None)  # PPO's; distillation has none

    times: list[tuple[float, float]] = []
    log_fn = runner.logger.log

    def record(*a: Any, **kw: Any) -> None:  # rsl-rl hands the per-iteration timings to its logger
        times.append((float(kw["collect_time"]), float(kw["learn_time"])))
        log_fn(*a, **kw)

    runner.logger.log = record  # type: ignore[method-assign]
    runner.learn(args.warmup + args.iterations)
    measured = times[args.warmup :]
    collect_s = sum(c for c, _ in measured) / len(measured)
    learn_s = sum(lr for _, lr in measured) / len(measured)
    steps = cfg.env.num_envs * cfg.runner.num_steps_per_env
    result = {
        "benchmark": "train",
        "config": os.path.relpath(args.config, REPO_ROOT),
        "num_envs": cfg.env.num_envs,
        "num_steps_per_env": cfg.runner.num_steps_per_env,
        "num_learning_epochs": cfg.runner.algorithm.num_learning_epochs,
        "num_mini_batches": getattr(cfg.runner.algorithm, "num_mini_batches", None),  # PPO only
        "runner": cfg.runner.class_name,
        "iterations": len(measured),
        "collect_s": round(collect_s, 3),
        "learn_s": round(learn_s, 3),
        "env_steps_per_s": round(steps / (collect_s + learn_s), 1),
        "collect_env_steps_per_s": round(steps / collect_s, 1),
        "actor_params": sum(q.numel() for q in actor.parameters()),
        "critic_params": sum(q.numel() for q in critic.parameters()) if critic is not None else 0,
        "torch_threads": threads,
        "env_build_s": round(build_s, 2),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        **machine(),
    }
    emit(result, args.json)
    return result
