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

Modules: :mod:`~shield_nav.training.config` (the typed config, its checks, rsl-rl's dict) and
:mod:`~shield_nav.training.runner` (runners, env, run folders, resume, signals, exports, the CLI) and
:mod:`~shield_nav.training.pipeline` (staged recipes: several runs in sequence from one config, resumable). Everything
public is re-exported here.
"""

from shield_nav.training.config import (
    ALGORITHM_CONFIGS,
    ANCHORED_ALGORITHM,
    CHECKPOINT_FORMAT_VERSION,
    MULTI_HYPOTHESIS_ALGORITHM,
    REPO_ROOT,
    SCHEDULED_ALGORITHM,
    ActorConfig,
    AlgorithmConfig,
    AnchoredPPOConfig,
    CriticConfig,
    DistillationConfig,
    DistributionConfig,
    ExpertConfig,
    MultiHypothesisDistillationConfig,
    PPOConfig,
    RunnerConfig,
    ScheduledDistillationConfig,
    TrainConfig,
    load_train_config,
    migrate_flat_algorithm,
    rsl_rl_train_cfg,
)
from shield_nav.training.runner import (
    ShieldNavDistillationRunner,
    ShieldNavRunner,
    build_parser,
    check_checkpoint,
    check_device,
    check_files,
    config_from_args,
    configure_threads,
    episode_means,
    main,
    make_env,
    make_runner,
    progress_line,
    read_checkpoint_infos,
    train,
)

__all__ = [
    "ALGORITHM_CONFIGS",
    "ANCHORED_ALGORITHM",
    "ActorConfig",
    "AlgorithmConfig",
    "AnchoredPPOConfig",
    "DistillationConfig",
    "MultiHypothesisDistillationConfig",
    "PPOConfig",
    "ScheduledDistillationConfig",
    "CHECKPOINT_FORMAT_VERSION",
    "CriticConfig",
    "DistributionConfig",
    "ExpertConfig",
    "MULTI_HYPOTHESIS_ALGORITHM",
    "REPO_ROOT",
    "RunnerConfig",
    "SCHEDULED_ALGORITHM",
    "ShieldNavDistillationRunner",
    "ShieldNavRunner",
    "TrainConfig",
    "build_parser",
    "check_checkpoint",
    "check_device",
    "check_files",
    "config_from_args",
    "configure_threads",
    "episode_means",
    "load_train_config",
    "migrate_flat_algorithm",
    "main",
    "make_env",
    "make_runner",
    "progress_line",
    "read_checkpoint_infos",
    "rsl_rl_train_cfg",
    "train",
]
