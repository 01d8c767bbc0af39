"""Training: typed config, run folders, rsl-rl's OnPolicyRunner with checkpoints, resume, signals and exports.

``train.py`` is a thin wrapper around :func:`main`. One run is::

    cfg = load_train_config("configs/train/dijkstra_cbf.yaml", overrides=["runner.algorithm.learning_rate=1e-4"])
    run_dir = train(cfg)

A run lives in ``<log_root>/<experiment_name>/<YYYY-mm-dd_HH-MM-SS>_<name>/``:

* ``params/config.yaml``: the resolved :class:`TrainConfig` (rebuild everything from it);
* ``git/``: the git revision, status and diff of this repository and of rsl-rl (rsl-rl's logger writes them);
* ``events.out.tfevents.*``: rsl-rl's scalars (losses, ``Train/mean_reward``, ``Perf/total_fps``, ...) plus the
  env's ``extras["log"]`` under their own names (``reward/<term>``, ``episode/success``, ...);
* ``model_<it>.pt``: rsl-rl checkpoints every ``runner.save_interval`` iterations, at the end and on interrupt,
  whose ``infos`` hold ``format_version``, the resolved config, and the logger's step/time totals;
* ``exported/policy.pt`` (TorchScript) and ``exported/policy.onnx``: the deterministic actor with an explicit
  GRU state, ``(obs, depth, h_in) -> (actions, h_out)``.

Modules: :mod:`~shield_nav.training.config` (the typed config, its checks, rsl-rl's dict),
:mod:`~shield_nav.training.checks` (the device, files and checkpoints checked before any work),
:mod:`~shield_nav.training.cli` (``train.py``'s parser and ``main``),
:mod:`~shield_nav.training.runner` (runners, env, run folders, resume, signals, exports) and
:mod:`~shield_nav.training.pipeline` (staged recipes: several runs in sequence from one config, resumable). Everything
public is re-exported here, lazily (PEP 562): importing this package costs only what the names used cost, so the
CLI answers ``--help`` or a bad config without importing torch and rsl-rl (docs/training.md).
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "config": (
        "ALGORITHM_CONFIGS", "ANCHORED_ALGORITHM", "ANCHOR_TARGETS", "CHECKPOINT_FORMAT_VERSION",
        "MULTI_HYPOTHESIS_ALGORITHM", "REPO_ROOT", "SCHEDULED_ALGORITHM", "ActorConfig", "AlgorithmConfig",
        "AnchoredPPOConfig", "CriticConfig", "DistillationConfig", "DistributionConfig", "ExpertConfig",
        "MultiHypothesisDistillationConfig", "PPOConfig", "RunnerConfig", "ScheduledDistillationConfig", "TrainConfig",
        "load_train_config", "migrate_flat_algorithm",
    ),
    "rsl_rl_cfg": ("rsl_rl_train_cfg",),
    "checks": ("check_checkpoint", "check_device", "check_files", "read_checkpoint_infos"),
    "cli": ("build_parser", "config_from_args", "main", "overrides_from_args"),
    "runner": (
        "ShieldNavDistillationRunner", "ShieldNavRunner", "configure_threads", "episode_means", "make_env",
        "make_runner", "progress_line", "train",
    ),
}  # fmt: skip
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """Import the submodule that defines ``name`` on first use (PEP 562)."""
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
