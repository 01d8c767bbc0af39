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
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import datetime
import glob
import inspect
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from rsl_rl.env import VecEnv
from rsl_rl.runners import DistillationRunner, OnPolicyRunner

from envs.config import ConfigError, load_config, require, to_dict, to_yaml
from envs.navigation import NavConfig
from shield_nav.anchored import ANCHOR_TARGETS
from shield_nav.baselines import EXPERTS, BaselineConfig, OracleConfig

CHECKPOINT_FORMAT_VERSION = 1
"""Version of the ``infos`` layout inside ``model_<it>.pt``; bump it and add a migration when it changes."""

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# ------------------------------------------------------------------------------------------------ config


@dataclass
class DistributionConfig:
    """The actor's output distribution (rsl-rl ``distribution_cfg``)."""

    class_name: str = "GaussianDistribution"
    """rsl-rl distribution class (``GaussianDistribution``: state-independent learnable std)."""
    init_std: float = 0.5
    """Initial action std, in normalised action units (actions live in [-1, 1])."""
    std_type: str = "scalar"
    """Std parameterisation: ``scalar`` or ``log``."""


@dataclass
class ActorConfig:
    """The actor model (rsl-rl ``actor`` dict); the keys are :class:`shield_nav.models.DepthGRUModel` arguments."""

    class_name: str = "shield_nav.models:DepthGRUModel"
    """Model class, ``module:Class``."""
    hidden_dims: list[int] = field(default_factory=lambda: [128, 64])
    """MLP head hidden sizes after the GRU."""
    activation: str = "elu"
    """MLP head activation (rsl-rl name)."""
    obs_normalization: bool = True
    """Running mean/std normalisation of the 1-D state groups (the depth image is already in [0, 1])."""
    cnn_channels: list[int] = field(default_factory=lambda: [8, 16, 32])
    """Output channels of each convolution."""
    cnn_kernel_sizes: list[int] = field(default_factory=lambda: [4, 3, 3])
    """Kernel size of each convolution."""
    cnn_strides: list[int] = field(default_factory=lambda: [4, 1, 1])
    """Stride of each convolution."""
    cnn_max_pool: list[bool] = field(default_factory=lambda: [False, True, True])
    """2 x 2 max pool after each convolution."""
    cnn_feature_dim: int = 64
    """Size of the visual feature f_CNN."""
    rnn_hidden_dim: int = 128
    """GRU hidden size."""
    rnn_num_layers: int = 1
    """Stacked GRU layers."""
    num_hypotheses: int = 1
    """Candidate actions of the head; ``K > 1`` acts with the best-scored one and needs
    ``algorithm.class_name: "shield_nav.distillation:MultiHypothesisDistillation"`` (docs/training.md)."""
    distribution_cfg: DistributionConfig = field(default_factory=DistributionConfig)
    """Output distribution."""


@dataclass
class CriticConfig:
    """The critic model (rsl-rl ``critic`` dict): an MLP over the privileged group only."""

    class_name: str = "MLPModel"
    """Model class (rsl-rl's ``MLPModel``)."""
    hidden_dims: list[int] = field(default_factory=lambda: [256, 128, 64])
    """Hidden sizes."""
    activation: str = "elu"
    """Activation (rsl-rl name)."""
    obs_normalization: bool = True
    """Running mean/std normalisation of the critic input."""


def _default_teacher() -> ActorConfig:
    return ActorConfig(class_name="MLPModel", hidden_dims=[256, 128, 64])


@dataclass
class AlgorithmConfig:
    """PPO (or Distillation) hyper-parameters (rsl-rl ``algorithm`` dict).

    Keys the chosen algorithm class does not take are dropped when the runner is built (PPO ignores
    ``gradient_length`` and ``loss_type``; Distillation ignores the PPO-only keys).
    """

    class_name: str = "PPO"
    """Algorithm class: ``PPO``; with ``runner.class_name: DistillationRunner`` rsl-rl's ``Distillation`` or, for a
    student with ``actor.num_hypotheses > 1``, ``shield_nav.distillation:MultiHypothesisDistillation``."""
    num_learning_epochs: int = 4
    """Passes over each rollout."""
    num_mini_batches: int = 4
    """Mini-batches per pass (recurrent: envs are split into this many groups; num_envs must be divisible)."""
    clip_param: float = 0.2
    """PPO ratio clip epsilon."""
    gamma: float = 0.99
    """Discount per 10 ms policy step (horizon ~ 1 / (1 - gamma) = 100 steps = 1 s)."""
    lam: float = 0.95
    """GAE lambda."""
    value_loss_coef: float = 1.0
    """Weight of the value loss."""
    entropy_coef: float = 0.005
    """Weight of the entropy bonus."""
    learning_rate: float = 3.0e-4
    """Initial Adam learning rate (adapted by the KL schedule)."""
    max_grad_norm: float = 1.0
    """Gradient clipping norm."""
    use_clipped_value_loss: bool = True
    """Clip the value update like the policy ratio."""
    schedule: str = "adaptive"
    """``adaptive`` (learning rate follows desired_kl) or ``fixed``."""
    desired_kl: float = 0.01
    """Target KL for the adaptive schedule."""
    normalize_advantage_per_mini_batch: bool = False
    """Normalise advantages per mini-batch instead of over the whole rollout."""
    gradient_length: int = 24
    """Distillation only: steps of behaviour-cloning loss accumulated per gradient step (the student's BPTT window)."""
    loss_type: str = "mse"
    """Distillation only: ``mse`` or ``huber`` between the student's mean action and the teacher's."""
    wta_epsilon: float = 0.05
    """Multi-hypothesis distillation (and kickstarting, ``anchor_target: expert``) only: share of the loss spread over
    the losing candidates, in [0, 1)."""
    selection_coef: float = 0.1
    """Multi-hypothesis distillation (and kickstarting) only: weight of the cross-entropy that trains the candidate
    scores."""
    lr_schedule: str = "constant"
    """Distillation only: ``constant`` (rsl-rl's) or ``cosine`` from ``learning_rate`` to ``lr_final`` over
    ``lr_schedule_iterations`` updates; ``cosine`` needs ``shield_nav.distillation:ScheduledDistillation`` (single
    head) or ``MultiHypothesisDistillation``."""
    lr_final: float = 1.0e-5
    """Distillation with ``lr_schedule: cosine`` only: the rate the cosine ends at."""
    lr_schedule_iterations: int = 0
    """Distillation with ``lr_schedule: cosine`` only: iterations the cosine takes; 0 = the run's
    ``max_iterations``."""
    replay_rollouts: int = 0
    """Distillation only: past rollouts kept for replay (dataset aggregation); 0 = rsl-rl's fit-once DAgger. Needs
    ``ScheduledDistillation`` or ``MultiHypothesisDistillation``; each costs ``num_envs x num_steps_per_env``
    observations of memory (128 x 24 depth images = 74 MB)."""
    replay_passes: int = 0
    """Distillation with replay only: kept rollouts fitted per update (each costs about one learning epoch)."""
    anchor_coef: float = 0.0
    """``shield_nav.anchored:AnchoredPPO`` only: weight of the anchor term, the distance of the actor's mean action
    from the reference's on the same states (PPO fine-tuning)."""
    anchor_target: str = "actor_init"
    """``shield_nav.anchored:AnchoredPPO`` only: the reference. ``actor_init``: the frozen ``runner.actor_init``
    actor, ``mean((mu - mu_ref)^2)``. ``expert``: the scripted expert of ``runner.expert`` (kickstarting), DAgger's
    loss (``wta_loss`` with ``wta_epsilon`` and ``selection_coef`` for a multi-hypothesis actor)."""


MULTI_HYPOTHESIS_ALGORITHM = "shield_nav.distillation:MultiHypothesisDistillation"
"""``runner.algorithm.class_name`` of a student with ``actor.num_hypotheses > 1``."""
SCHEDULED_ALGORITHM = "shield_nav.distillation:ScheduledDistillation"
"""``runner.algorithm.class_name`` of a single-head student with a learning-rate schedule."""
ANCHORED_ALGORITHM = "shield_nav.anchored:AnchoredPPO"
"""``runner.algorithm.class_name`` of PPO fine-tuning anchored to its ``runner.actor_init`` actor."""


def _default_expert_params() -> BaselineConfig:
    return BaselineConfig(oracle=OracleConfig(episode_goal=True))


@dataclass
class ExpertConfig:
    """A scripted privileged expert: the teacher of oracle DAgger, or the reference of kickstarting PPO."""

    kind: str = ""
    """``oracle``: the geodesic-descent oracle of :mod:`shield_nav.baselines` labels every state the student visits
    (with ``teacher.class_name: "shield_nav.models:ExpertTeacher"`` and ``obs_groups.teacher: [expert]``); no
    ``teacher_checkpoint`` is needed; with ``AnchoredPPO`` and ``algorithm.anchor_target: expert``, the actions
    the PPO actor is held near. Empty: the trained teacher of ``teacher_checkpoint``."""
    params: BaselineConfig = field(default_factory=_default_expert_params)
    """The expert's parameters (:class:`shield_nav.baselines.BaselineConfig`; ``oracle.episode_goal`` defaults to
    true here: descend the field of the episode's goal point)."""


@dataclass
class RunnerConfig:
    """rsl-rl runner train_cfg (everything but the env)."""

    class_name: str = "OnPolicyRunner"
    """``OnPolicyRunner`` (PPO) or ``DistillationRunner`` (the actor imitates a trained privileged teacher)."""

    num_steps_per_env: int = 24
    """Rollout length per env per iteration (also the truncated-BPTT window of the GRU)."""
    save_interval: int = 50
    """Write ``model_<it>.pt`` every this many iterations."""
    obs_groups: dict[str, list[str]] = field(
        default_factory=lambda: {"actor": ["depth", "state"], "critic": ["critic"]}
    )
    """Observation sets -> env observation groups."""
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    """PPO."""
    actor: ActorConfig = field(default_factory=ActorConfig)
    """Actor model."""
    critic: CriticConfig = field(default_factory=CriticConfig)
    """Critic model (PPO only)."""
    teacher: ActorConfig = field(default_factory=_default_teacher)
    """Distillation only: the teacher model (keys its class does not take, e.g. ``cnn_*`` for ``MLPModel``, are
    dropped); its weights come from ``teacher_checkpoint``."""
    teacher_checkpoint: str = ""
    """Distillation only: the teacher's PPO checkpoint (``model_<it>.pt`` or ``checkpoints/<name>/model.pt``)."""
    student_init: str = ""
    """Distillation only, optional: a distillation checkpoint whose *student* weights (and observation normaliser)
    start this run, e.g. the previous round's ``checkpoints/<f>_distilled/model.pt`` when re-distilling from a longer
    trained teacher, and its stored curriculum levels when the env count matches. The optimizer and the iteration
    count start fresh; empty = a randomly initialised student."""
    actor_init: str = ""
    """PPO only, optional: a checkpoint whose actor starts this run's actor (PPO fine-tuning of a distilled student):
    a distillation checkpoint's ``student_state_dict`` (e.g. ``checkpoints/student_3ms/model.pt``) or a PPO
    checkpoint's ``actor_state_dict``, with its observation normaliser and action std, and its stored curriculum
    levels when the env count matches. The critic, optimizer and iteration count start fresh."""
    critic_warmup_iterations: int = 0
    """PPO only: for the first this many iterations of a new run the actor's parameters are frozen, so the fresh
    critic learns the values of the loaded actor before its advantages move the policy (needs
    ``algorithm.schedule: fixed``: with a frozen actor the KL is 0 and the adaptive rule would raise the rate)."""
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    """Optional: a scripted expert as the distillation teacher, or as the kickstarting reference of
    ``AnchoredPPO`` (see :class:`ExpertConfig`)."""
    init_at_random_ep_len: bool = True
    """Start the first rollout at random episode times, to decorrelate the envs."""
    check_for_nan: bool = True
    """Fail on NaN observations/rewards (rsl-rl check)."""
    logger: str = "tensorboard"
    """rsl-rl log writer (``tensorboard``)."""


@dataclass
class TrainConfig:
    """One training run: the task, the learner and the bookkeeping."""

    name: str = "run"
    """Run name, the suffix of the run folder (the config files set it: ``dijkstra_cbf``, ...)."""
    experiment_name: str = "shield_nav"
    """Experiment folder under ``log_root``."""
    log_root: str = "logs"
    """Root of the run folders (``--log-dir``)."""
    seed: int = 0
    """Torch seed (``--seed`` sets it and ``env.seed``)."""
    device: str = "cpu"
    """Learner device (``cpu``, ``cuda``, ``cuda:0``); the env is CPU (numpy) either way."""
    max_iterations: int = 1500
    """Total PPO iterations of the run; a resumed run continues until it reaches this count."""
    num_threads: int = 0
    """Torch intra-op threads; 0 picks the CPUs this process may use (os.sched_getaffinity)."""
    env: NavConfig = field(default_factory=NavConfig)
    """The task (``envs.navigation.NavConfig``)."""
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    """The learner."""

    def validate(self, prefix: str = "") -> None:
        """Cross-field checks naming the key."""
        require(self.max_iterations >= 1, f"{prefix}max_iterations", f"must be >= 1, got {self.max_iterations}")
        require(self.num_threads >= 0, f"{prefix}num_threads", "must be >= 0")
        require(
            self.device == "cpu" or self.device.startswith("cuda"),
            f"{prefix}device",
            f"must be 'cpu' or 'cuda[:i]', got {self.device!r}",
        )
        r = self.runner
        require(r.num_steps_per_env >= 1, f"{prefix}runner.num_steps_per_env", "must be >= 1")
        require(r.save_interval >= 1, f"{prefix}runner.save_interval", "must be >= 1")
        mb = r.algorithm.num_mini_batches
        require(
            mb >= 1 and self.env.num_envs % mb == 0,
            f"{prefix}runner.algorithm.num_mini_batches",
            f"must divide env.num_envs ({self.env.num_envs}) for the recurrent generator, got {mb}",
        )
        require(r.algorithm.schedule in ("adaptive", "fixed"), f"{prefix}runner.algorithm.schedule", "adaptive|fixed")
        runners = ("OnPolicyRunner", "DistillationRunner")
        require(
            r.class_name in runners, f"{prefix}runner.class_name", f"must be one of {runners}, got {r.class_name!r}"
        )
        distill = r.class_name == "DistillationRunner"
        multi = r.actor.num_hypotheses > 1
        algos = ("PPO", ANCHORED_ALGORITHM)
        if distill:
            algos = (MULTI_HYPOTHESIS_ALGORITHM,) if multi else ("Distillation", SCHEDULED_ALGORITHM)
        got = r.algorithm.class_name
        require(r.actor.num_hypotheses >= 1, f"{prefix}runner.actor.num_hypotheses", "must be >= 1")
        require(distill or not multi or r.actor_init, f"{prefix}runner.actor.num_hypotheses",
                "> 1 only with DistillationRunner or PPO fine-tuning from runner.actor_init")  # fmt: skip
        anchored = got == ANCHORED_ALGORITHM
        require(r.algorithm.anchor_coef >= 0.0 and (anchored or r.algorithm.anchor_coef == 0.0),
                f"{prefix}runner.algorithm.anchor_coef",
                f"must be >= 0, and > 0 only with runner.algorithm.class_name {ANCHORED_ALGORITHM!r}; got "
                f"{r.algorithm.anchor_coef} with {got!r}")  # fmt: skip
        require(not anchored or r.actor_init, f"{prefix}runner.actor_init",
                f"is required by {ANCHORED_ALGORITHM!r}: it is the actor the fine-tuning starts from")  # fmt: skip
        require(r.algorithm.anchor_target in ANCHOR_TARGETS, f"{prefix}runner.algorithm.anchor_target",
                f"must be one of {ANCHOR_TARGETS}, got {r.algorithm.anchor_target!r}")  # fmt: skip
        kickstart = anchored and r.algorithm.anchor_target == "expert"
        require(not kickstart or r.expert.kind, f"{prefix}runner.expert.kind",
                "must be set with runner.algorithm.anchor_target 'expert' (the expert the actor is held near)")
        require(got in algos, f"{prefix}runner.algorithm.class_name",
                f"must be one of {algos} with runner.class_name {r.class_name!r} and actor.num_hypotheses "
                f"{r.actor.num_hypotheses}, got {got!r}")  # fmt: skip
        require(r.algorithm.lr_schedule in ("constant", "cosine"), f"{prefix}runner.algorithm.lr_schedule",
                f"must be 'constant' or 'cosine', got {r.algorithm.lr_schedule!r}")  # fmt: skip
        require(r.algorithm.lr_schedule == "constant" or got in (SCHEDULED_ALGORITHM, MULTI_HYPOTHESIS_ALGORITHM),
                f"{prefix}runner.algorithm.lr_schedule",
                f"'cosine' needs runner.algorithm.class_name {SCHEDULED_ALGORITHM!r} or {MULTI_HYPOTHESIS_ALGORITHM!r}"
                f", got {got!r}")  # fmt: skip
        require(r.algorithm.lr_schedule == "constant" or 0.0 < r.algorithm.lr_final <= r.algorithm.learning_rate,
                f"{prefix}runner.algorithm.lr_final",
                f"must be in (0, runner.algorithm.learning_rate = {r.algorithm.learning_rate}], "
                f"got {r.algorithm.lr_final}")  # fmt: skip
        require(r.algorithm.lr_schedule_iterations >= 0, f"{prefix}runner.algorithm.lr_schedule_iterations",
                "must be >= 0 (0 = max_iterations)")  # fmt: skip
        ours = (SCHEDULED_ALGORITHM, MULTI_HYPOTHESIS_ALGORITHM)
        rr, rp = r.algorithm.replay_rollouts, r.algorithm.replay_passes
        require(rr == 0 or got in ours, f"{prefix}runner.algorithm.replay_rollouts",
                f"> 0 needs runner.algorithm.class_name one of {ours}, got {got!r}")  # fmt: skip
        require(rr >= 0 and 0 <= rp <= rr and (rr > 0) == (rp > 0), f"{prefix}runner.algorithm.replay_passes",
                f"needs 0 <= replay_passes <= replay_rollouts, both 0 or both > 0; got {rp} and {rr}")  # fmt: skip
        require(0.0 <= r.algorithm.wta_epsilon < 1.0, f"{prefix}runner.algorithm.wta_epsilon", "must be in [0, 1)")
        require(r.algorithm.selection_coef >= 0.0, f"{prefix}runner.algorithm.selection_coef", "must be >= 0")
        require(distill or not r.student_init, f"{prefix}runner.student_init", "only with DistillationRunner")
        require(not distill or not r.actor_init, f"{prefix}runner.actor_init", "only with OnPolicyRunner (PPO)")
        require(r.critic_warmup_iterations >= 0, f"{prefix}runner.critic_warmup_iterations", "must be >= 0")
        require(r.critic_warmup_iterations == 0 or (not distill and r.algorithm.schedule == "fixed"),
                f"{prefix}runner.critic_warmup_iterations",
                "needs runner.class_name OnPolicyRunner and runner.algorithm.schedule 'fixed'")  # fmt: skip
        for key in ("student", "teacher") if distill else ("actor", "critic"):
            require(key in r.obs_groups, f"{prefix}runner.obs_groups.{key}", "is required")
        require(r.algorithm.loss_type in ("mse", "huber"), f"{prefix}runner.algorithm.loss_type", "mse|huber")
        require(r.algorithm.gradient_length >= 1, f"{prefix}runner.algorithm.gradient_length", "must be >= 1")
        uses_expert_obs = any("expert" in groups for groups in r.obs_groups.values())
        require(not uses_expert_obs or r.expert.kind, f"{prefix}runner.expert.kind",
                "must be set when an obs group reads the 'expert' observation")  # fmt: skip
        if r.expert.kind:
            require(r.expert.kind in EXPERTS, f"{prefix}runner.expert.kind",
                    f"unknown expert {r.expert.kind!r}; known: {sorted(EXPERTS)}")  # fmt: skip
            require(distill or kickstart, f"{prefix}runner.expert.kind",
                    "only with runner.class_name DistillationRunner, or AnchoredPPO with anchor_target 'expert'")
            require(not distill or r.obs_groups.get("teacher") == ["expert"], f"{prefix}runner.obs_groups.teacher",
                    f"must be [expert] with runner.expert.kind {r.expert.kind!r}")  # fmt: skip
            require(not distill or r.teacher.class_name.endswith("ExpertTeacher"), f"{prefix}runner.teacher.class_name",
                    "must be 'shield_nav.models:ExpertTeacher' with a scripted expert")  # fmt: skip
        uses_teacher_obs = any("teacher" in groups for groups in r.obs_groups.values())
        require(not uses_teacher_obs or self.env.local_map.enabled, f"{prefix}env.local_map.enabled",
                "must be true when an obs group reads the 'teacher' observation")  # fmt: skip


def load_train_config(
    files: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    overrides: Sequence[str] | dict | None = None,
    base: TrainConfig | None = None,
) -> TrainConfig:
    """Load a :class:`TrainConfig` from YAML file(s) (with ``defaults:`` includes) and dotted overrides.

    Raises:
        ConfigError: Naming the dotted key of the first unknown key or bad value, before any work.
    """
    return load_config(TrainConfig, files=files, overrides=overrides, base=base)


def _constructor_names(class_name: str) -> set[str] | None:
    """Parameter names ``class_name``'s constructor chain takes (None: it takes any keyword).

    A subclass that forwards ``**kwargs`` to its parent (shield_nav.anchored.AnchoredPPO -> PPO) takes what the first
    class up its MRO without ``**kwargs`` takes; if every ``__init__`` takes ``**kwargs``, anything is passed on.
    """
    from rsl_rl.utils import resolve_callable

    names: set[str] = set()
    for klass in resolve_callable(class_name).__mro__:
        if "__init__" not in vars(klass):
            continue
        params = inspect.signature(vars(klass)["__init__"]).parameters
        names.update(params)
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return names
    return None


def check_algorithm_keys(cfg: TrainConfig, keys: Sequence[str] | None = None) -> None:
    """An algorithm key set away from its default that the chosen algorithm does not take is an error.

    ``runner.algorithm`` holds the parameters of every algorithm (PPO, distillation, multi-hypothesis, anchored);
    the runner passes each class only what its constructor takes, so without this check e.g.
    ``--set runner.algorithm.wta_epsilon=0.9`` on plain PPO would train and drop the key without a word.
    """
    algo = cfg.runner.algorithm
    names = _constructor_names(algo.class_name)
    if names is None:
        return
    defaults = AlgorithmConfig()
    for f in dataclasses.fields(AlgorithmConfig):
        if f.name == "class_name" or f.name in names or (keys is not None and f.name not in keys):
            continue
        if keys is not None or getattr(algo, f.name) != getattr(defaults, f.name):
            raise ConfigError(f"config key 'runner.algorithm.{f.name}': {algo.class_name} does not take it (set to "
                              f"{getattr(algo, f.name)!r}); it applies to another algorithm class")  # fmt: skip


def _accepted(class_name: str, kwargs: dict) -> dict:
    """``kwargs`` restricted to what ``class_name``'s constructor takes (all of them if it takes ``**kwargs``)."""
    names = _constructor_names(class_name)
    if names is None:
        return kwargs
    return {k: v for k, v in kwargs.items() if k in names or k == "class_name"}


def rsl_rl_train_cfg(cfg: TrainConfig) -> dict:
    """The plain ``train_cfg`` dict the rsl-rl runner takes (a fresh copy: rsl-rl may mutate it).

    PPO gets ``actor``/``critic``; distillation gets ``student`` (the ``actor`` section: the deployable depth model)
    and ``teacher``. Model and algorithm keys their classes do not take are dropped.
    """
    d = to_dict(cfg.runner)
    for key in ("init_at_random_ep_len", "class_name", "teacher_checkpoint", "student_init", "expert",
                "actor_init", "critic_warmup_iterations"):
        d.pop(key)
    teacher = d.pop("teacher")
    if cfg.runner.class_name == "DistillationRunner":
        d["student"] = d.pop("actor")
        d["teacher"] = teacher
        d.pop("critic")
    if d["algorithm"]["lr_schedule_iterations"] == 0:
        d["algorithm"]["lr_schedule_iterations"] = cfg.max_iterations
    if d["algorithm"]["class_name"] in (SCHEDULED_ALGORITHM, MULTI_HYPOTHESIS_ALGORITHM):
        d["algorithm"]["seed"] = cfg.seed  # the draw of replayed rollouts
    for key in ("actor", "critic", "student", "teacher", "algorithm"):
        if key in d:
            d[key] = _accepted(d[key]["class_name"], d[key])
    d["experiment_name"] = cfg.experiment_name
    d["run_name"] = cfg.name
    d["seed"] = cfg.seed
    return copy.deepcopy(d)


# ------------------------------------------------------------------------------------------------ runner


class _VersionedSave:
    """Mixin over an rsl-rl runner: ``save`` writes versioned ``infos`` (format, resolved config, totals)."""

    def __init__(self, env: VecEnv, train_cfg: dict, log_dir: str | None, device: str, config: TrainConfig) -> None:
        """Build the stock runner; ``config`` is stored (resolved) in every checkpoint."""
        super().__init__(env, train_cfg, log_dir=log_dir, device=device)
        self.config_dict = to_dict(config)

    def save(self, path: str, infos: dict | None = None) -> None:
        """Save like rsl-rl, with ``infos = {format_version, config, logger totals, versions, ...}``."""
        full = {
            "format_version": CHECKPOINT_FORMAT_VERSION,
            "config": self.config_dict,
            "tot_timesteps": int(self.logger.tot_timesteps),
            "tot_time": float(self.logger.tot_time),
            "torch_version": torch.__version__,
            "saved_at": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        if hasattr(self.env, "curriculum_levels"):
            full["curriculum_levels"] = self.env.curriculum_levels  # restored by --resume
        full.update(infos or {})
        super().save(path, infos=full)


class ShieldNavRunner(_VersionedSave, OnPolicyRunner):
    """rsl-rl's ``OnPolicyRunner`` (PPO); only ``save`` differs: every checkpoint carries versioned ``infos``."""


class ShieldNavDistillationRunner(_VersionedSave, DistillationRunner):
    """rsl-rl's ``DistillationRunner`` (student imitates teacher, DAgger-style); versioned ``infos`` as above."""


def make_runner(env: VecEnv, cfg: TrainConfig, log_dir: str | None, device: str) -> OnPolicyRunner:
    """The runner of ``cfg.runner.class_name`` over ``env``."""
    cls = ShieldNavDistillationRunner if cfg.runner.class_name == "DistillationRunner" else ShieldNavRunner
    return cls(env, rsl_rl_train_cfg(cfg), log_dir=log_dir, device=device, config=cfg)


def read_checkpoint_infos(path: str | os.PathLike) -> dict:
    """The ``infos`` of a checkpoint, migrated to the current format (``ValueError`` if unknown or unreadable)."""
    ckpt = check_checkpoint(path, "checkpoint")
    infos = ckpt.get("infos") or {}
    version = infos.get("format_version")
    if version is None:
        raise ValueError(f"{path}: no format_version in infos; not written by shield_nav.training")
    if version > CHECKPOINT_FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {version} is newer than this code ({CHECKPOINT_FORMAT_VERSION})")
    # Version 1 is current; future migrations go here (if version == 1: ...).
    return infos


class _StopTraining(Exception):
    """Raised at an iteration boundary after SIGINT/SIGTERM."""


class _StopFlag:
    """SIGINT/SIGTERM handler: the first signal asks to stop after the current iteration, a second one aborts."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt  # second signal: abort now, without saving
        self.signum = signum
        print(f"\n[train] {signal.Signals(signum).name}: saving a checkpoint after this iteration", flush=True)


# ------------------------------------------------------------------------------------------------ run


def configure_threads(num_threads: int) -> int:
    """Set torch's intra-op threads (0: the CPUs this process may use) and one inter-op thread; return the count."""
    n = num_threads or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    torch.set_num_threads(n)
    with contextlib.suppress(RuntimeError):  # only allowed before the first parallel op; harmless to skip
        torch.set_num_interop_threads(1)  # PPO has no independent ops to overlap
    return n


def make_env(cfg: TrainConfig) -> VecEnv:
    """The rsl-rl VecEnv of the task (CPU, numpy inside; tensors on the learner device)."""
    from envs.navigation import NavigationEnv
    from envs.rsl_rl import RslRlVecEnv

    expert = None
    if cfg.runner.expert.kind:
        expert = EXPERTS[cfg.runner.expert.kind](cfg.runner.expert.params)
    return RslRlVecEnv(NavigationEnv(config=cfg.env), device=cfg.device, expert=expert)


def _randomize_episode_lengths(env: VecEnv) -> None:
    """Start each env at a uniform random time of its episode (rsl-rl's ``init_at_random_ep_len``).

    Done here because rsl-rl's runner calls ``int(env.max_episode_length)``, which fails for the task's
    per-env limits (N,); this draws ``episode_length_buf[i] ~ U{0, ..., max_episode_length[i] - 1}``.
    """
    limit = torch.as_tensor(env.max_episode_length, dtype=torch.float32).expand(env.num_envs)
    env.episode_length_buf = (torch.rand(env.num_envs) * limit).long()


def _new_run_dir(cfg: TrainConfig) -> str:
    """A fresh ``<log_root>/<experiment>/<stamp>_<name>`` folder, claimed atomically.

    Runs of the same config started within the same second (e.g. several seeds launched together) would otherwise
    share one folder and overwrite each other's checkpoints: the second and later get ``_2``, ``_3``, ...
    """
    stamp = datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    base = os.path.join(cfg.log_root, cfg.experiment_name, f"{stamp}_{cfg.name}")
    os.makedirs(os.path.dirname(base), exist_ok=True)
    path, k = base, 1
    while True:
        try:
            os.mkdir(path)  # fails if another run claimed it first
            break
        except FileExistsError:
            k += 1
            path = f"{base}_{k}"
    os.makedirs(os.path.join(path, "params"), exist_ok=True)
    return path


def check_device(device: str) -> None:
    """Fail before any folder is made if ``device`` names CUDA that this torch build or machine does not have."""
    if not device.startswith("cuda"):
        return
    if not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"a CUDA {torch.version.cuda} build"
        raise ConfigError(f"config key 'device': {device!r} asked, but no CUDA device is usable here (torch "
                          f"{torch.__version__} is {build}); use --device cpu")  # fmt: skip
    index = int(device.split(":", 1)[1]) if ":" in device else 0
    if index >= torch.cuda.device_count():
        raise ConfigError(f"config key 'device': {device!r} asked, but only {torch.cuda.device_count()} CUDA "
                          "device(s) are visible")  # fmt: skip


def check_checkpoint(path: str | os.PathLike, what: str) -> dict:
    """Load a checkpoint on the CPU, or fail with a message that names it and the flag/key it came from."""
    if not os.path.isfile(path):
        raise ConfigError(f"{what}: no such file {str(path)!r}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # any reader error means the same thing to the user: unreadable
        size = os.path.getsize(path)
        raise ConfigError(f"{what}: {str(path)!r} ({size} bytes) is not a readable torch checkpoint, e.g. truncated "
                          f"by an interrupted copy or save ({type(err).__name__}: {err})") from None  # fmt: skip
    if not isinstance(ckpt, dict):
        raise ConfigError(f"{what}: {str(path)!r} holds a {type(ckpt).__name__}, not a checkpoint dict")
    return ckpt


def check_files(cfg: TrainConfig, resume: str | os.PathLike | None = None) -> None:
    """Fail before any work if a file the run needs is missing or unreadable, or the device is not there."""
    check_device(cfg.device)
    if resume is not None:
        ckpt = check_checkpoint(resume, "--resume")
        if "iter" not in ckpt:
            raise ConfigError(f"--resume: {str(resume)!r} has no iteration count: not a model_<it>.pt of a run")
    distill = cfg.runner.class_name == "DistillationRunner"
    if distill and resume is None and not cfg.runner.expert.kind and not os.path.isfile(cfg.runner.teacher_checkpoint):
        raise ConfigError(
                f"config key 'runner.teacher_checkpoint': no such file {cfg.runner.teacher_checkpoint!r} "
                "(train the teacher first: python train.py --config configs/train/teacher_<formulation>.yaml)"
            )
    if distill and resume is None and cfg.runner.student_init and not os.path.isfile(cfg.runner.student_init):
        raise ConfigError(f"config key 'runner.student_init': no such file {cfg.runner.student_init!r}")
    if resume is None and cfg.runner.actor_init and not os.path.isfile(cfg.runner.actor_init):
        raise ConfigError(f"config key 'runner.actor_init': no such file {cfg.runner.actor_init!r}")


def _init_student(runner: Any, path: str, device: str) -> dict:
    """Load a checkpoint's student weights into the runner's student; return the checkpoint's ``infos``.

    A single-head student initialises a multi-hypothesis one: every candidate starts as its head
    (:func:`shield_nav.models.expand_single_head`), so training starts from the single-head policy.
    """
    from shield_nav.models import expand_single_head

    student = runner.alg._raw_student
    ckpt = torch.load(path, map_location=device, weights_only=False)
    weights = ckpt.get("student_state_dict")
    if weights is None:
        raise ConfigError(f"config key 'runner.student_init': {path!r} holds no student (not a distillation run)")
    single = not any(key.startswith("mlp.0.0.") for key in weights)
    if getattr(student, "num_hypotheses", 1) > 1 and single:
        weights = expand_single_head(weights, student)
        print(f"[train] single-head student expanded to {student.num_hypotheses} hypotheses", flush=True)
    student.load_state_dict(weights)
    return ckpt.get("infos") or {}


def _restore_levels(env: Any, levels: list[int] | None) -> None:
    """Put the envs back on the curriculum levels a checkpoint stored (same env count only)."""
    if levels is not None and hasattr(env, "set_curriculum_levels") and len(levels) == env.num_envs:
        env.set_curriculum_levels(levels)
        print(f"[train] curriculum levels restored (mean {sum(levels) / len(levels):.2f})", flush=True)


def episode_means(ep_extras: list[dict], keys: tuple[str, ...]) -> dict[str, tuple[float, int]]:
    """Mean and count of each key over the episodes that ended this iteration (rsl-rl's ``ep_extras``)."""
    out = {}
    for key in keys:
        vals = [torch.as_tensor(e[key], dtype=torch.float64).reshape(-1) for e in ep_extras if key in e]
        flat = torch.cat(vals) if vals else torch.zeros(0, dtype=torch.float64)
        out[key] = (float(flat.mean()) if flat.numel() else math.nan, int(flat.numel()))
    return out


def progress_line(logger: Any, it: int, total_it: int, extras: dict[str, tuple[float, int]]) -> str:
    """One compact line per iteration: iteration, env-steps/s, success, curriculum level, elapsed and ETA."""
    done = it + 1
    fps = logger.tot_timesteps / logger.tot_time if logger.tot_time > 0 else 0.0
    eta = logger.tot_time / max(done, 1) * max(total_it - done, 0)
    succ, n_ep = extras.get("episode/success", (math.nan, 0))
    level, _ = extras.get("curriculum/mean_level", (math.nan, 0))

    def hms(t: float) -> str:
        t = int(t)
        return f"{t // 3600}:{t // 60 % 60:02d}:{t % 60:02d}"

    succ_s = f"{100 * succ:5.1f} % of {n_ep:3d} ep" if n_ep else "   - (no episode ended)"
    level_s = f"{level:5.2f}" if math.isfinite(level) else "  -  "
    return (f"[train] it {done:>{len(str(total_it))}}/{total_it} | {fps:7.0f} env-steps/s | success {succ_s} | "
            f"level {level_s} | {hms(logger.tot_time)} elapsed, ETA {hms(eta)}")  # fmt: skip


def train(
    cfg: TrainConfig,
    resume: str | os.PathLike | None = None,
    env_factory: Callable[[TrainConfig], VecEnv] = make_env,
) -> str:
    """Train (or resume) one run; return its folder.

    Args:
        cfg: The resolved config.
        resume: A ``model_<it>.pt`` to continue from: weights, optimizer, normalisers and the iteration count
            are restored, logging continues in the checkpoint's folder (tensorboard curves continue at ``it + 1``),
            and training runs until ``cfg.max_iterations`` iterations exist in total.
        env_factory: Builds the VecEnv from ``cfg`` (tests pass a small synthetic env).
    """
    rank = int(os.getenv("RANK", "0"))
    world = int(os.getenv("WORLD_SIZE", "1"))
    device = cfg.device
    if world > 1:  # torchrun: one process per GPU; rsl-rl's runner initialises NCCL and averages gradients
        if not device.startswith("cuda"):
            raise ConfigError("config key 'device': multi-process training (WORLD_SIZE > 1) needs 'cuda'")
        device = f"cuda:{int(os.getenv('LOCAL_RANK', '0'))}"
    check_files(cfg, resume)
    threads = configure_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed + rank)
    print(f"[train] torch {torch.__version__}: {threads} intra-op thread(s), 1 inter-op; device {device}", flush=True)

    if resume is not None and glob.glob(os.path.join(os.path.dirname(os.path.abspath(resume)), "events.out.tfevents*")):
        run_dir = os.path.dirname(os.path.abspath(resume))
    elif resume is not None:
        # A packaged policy (checkpoints/<name>/model.pt) has no run folder: continue in a new one under log_dir.
        run_dir = _new_run_dir(cfg) if rank == 0 else None
    else:
        run_dir = _new_run_dir(cfg) if rank == 0 else None
    if rank == 0:
        os.makedirs(os.path.join(run_dir, "params"), exist_ok=True)
        with open(os.path.join(run_dir, "params", "config.yaml"), "w", encoding="utf-8") as f:
            f.write(to_yaml(cfg))
        print(f"[train] run folder: {run_dir}", flush=True)

    t0 = time.perf_counter()
    env = env_factory(dataclasses.replace(cfg, device=device))
    print(f"[train] env: {env.num_envs} envs built in {time.perf_counter() - t0:.1f} s", flush=True)
    runner = make_runner(env, cfg, log_dir=run_dir, device=device)
    runner.add_git_repo_to_log(REPO_ROOT)

    start_it = 0
    if cfg.runner.class_name == "DistillationRunner" and cfg.runner.expert.kind:
        runner.alg.teacher_loaded = True  # the scripted expert has no weights to load
        print(f"[train] teacher: the scripted '{cfg.runner.expert.kind}' expert (obs group 'expert')", flush=True)
    if cfg.runner.class_name == "DistillationRunner" and resume is None and not cfg.runner.expert.kind:
        runner.load(cfg.runner.teacher_checkpoint, map_location=device)  # actor weights -> teacher only
        print(f"[train] teacher loaded from {cfg.runner.teacher_checkpoint}", flush=True)
    if cfg.runner.class_name == "DistillationRunner" and resume is None and cfg.runner.student_init:
        infos = _init_student(runner, cfg.runner.student_init, device)
        print(f"[train] student initialised from {cfg.runner.student_init}", flush=True)
        _restore_levels(env, infos.get("curriculum_levels"))
    if cfg.runner.actor_init and resume is None:
        ckpt = torch.load(cfg.runner.actor_init, map_location=device, weights_only=False)
        weights = ckpt.get("student_state_dict") or ckpt.get("actor_state_dict")
        if weights is None:
            raise ConfigError(f"config key 'runner.actor_init': {cfg.runner.actor_init!r} holds no actor or student")
        runner.alg._raw_actor.load_state_dict(weights)
        print(f"[train] actor initialised from {cfg.runner.actor_init}", flush=True)
        _restore_levels(env, (ckpt.get("infos") or {}).get("curriculum_levels"))
    if resume is not None:
        # A scripted expert saved no teacher weights (an empty dict): load everything else.
        load_cfg = {"student": True, "optimizer": True, "iteration": True} if cfg.runner.expert.kind else None
        infos = runner.load(str(resume), load_cfg=load_cfg, map_location=device) or {}
        start_it = runner.current_learning_iteration + 1  # the checkpoint holds a finished iteration
        runner.current_learning_iteration = start_it
        runner.logger.tot_timesteps = int(infos.get("tot_timesteps", 0))
        runner.logger.tot_time = float(infos.get("tot_time", 0.0))
        _restore_levels(env, infos.get("curriculum_levels"))
        print(f"[train] resumed from {resume}: continuing at iteration {start_it}", flush=True)
    remaining = cfg.max_iterations - start_it
    # Critic warm-up: iterations [0, warmup_end) run with a frozen actor (also when a run resumes inside them).
    warmup_end = cfg.runner.critic_warmup_iterations if cfg.runner.class_name == "OnPolicyRunner" else 0
    actor_params = list(runner.alg._raw_actor.parameters()) if start_it < warmup_end else []
    for p in actor_params:
        p.requires_grad_(False)
    if actor_params:
        print(f"[train] critic warm-up: the actor is frozen until iteration {warmup_end}", flush=True)

    # Stop cleanly at the next iteration boundary on SIGINT/SIGTERM: rsl-rl's logger.log runs once per iteration,
    # right after the update, so wrapping it gives a hook without copying the runner's loop.
    stop = _StopFlag()
    log_fn = runner.logger.log

    def log_then_check(*args: Any, **kwargs: Any) -> None:
        # The logger's ETA divides tot_time by the iterations since start_it; tot_time is restored on --resume and
        # spans the whole run, so count from iteration 0 (else a resumed run prints an ETA of days).
        if "start_it" in kwargs:
            kwargs["start_it"] = 0
        extras = episode_means(runner.logger.ep_extras, ("episode/success", "curriculum/mean_level"))
        log_fn(*args, **kwargs)
        print(progress_line(runner.logger, kwargs.get("it", runner.current_learning_iteration),
                            kwargs.get("total_it", cfg.max_iterations), extras), flush=True)  # fmt: skip
        if actor_params and runner.current_learning_iteration + 1 >= warmup_end:
            for p in actor_params:
                p.requires_grad_(True)
            actor_params.clear()
            print(f"[train] critic warm-up done: the actor trains from iteration {warmup_end}", flush=True)
        if stop.signum is not None:
            raise _StopTraining

    runner.logger.log = log_then_check  # type: ignore[method-assign]
    interrupted = False
    stop.install()
    try:
        if remaining > 0:
            if cfg.runner.init_at_random_ep_len and resume is None:
                _randomize_episode_lengths(env)
            runner.learn(remaining, init_at_random_ep_len=False)
        else:
            print(f"[train] nothing to do: {start_it} >= max_iterations ({cfg.max_iterations})", flush=True)
    except _StopTraining:
        interrupted = True
    finally:
        stop.restore()

    if rank == 0:
        it = runner.current_learning_iteration
        if interrupted:
            runner.save(os.path.join(run_dir, f"model_{it}.pt"), infos={"interrupted": interrupted})
        runner.logger.stop_logging_writer()
        if runner.logger.writer is not None and hasattr(runner.logger.writer, "close"):
            runner.logger.writer.close()
        from shield_nav.models import DepthGRUModel, export_policy

        policy = runner.alg.get_policy()
        if isinstance(policy, DepthGRUModel):
            try:
                paths = export_policy(policy, os.path.join(run_dir, "exported"))
            except Exception:
                # The checkpoint is on disk. A known cause: TorchScript re-reads the model's source file, so editing
                # shield_nav/models.py while a run trains can break the run's final export (not its weights).
                print(f"[train] the export failed; model_{it}.pt is saved. Re-export it with: python -m "
                      f"shield_nav.package {os.path.join(run_dir, f'model_{it}.pt')} --name <policy name>",
                      file=sys.stderr, flush=True)  # fmt: skip
                raise
            print(f"[train] exported {paths['jit']} and {paths['onnx']}", flush=True)
        else:  # a privileged teacher: not deployable (it reads the local ESDF map), so nothing is exported
            print(f"[train] not exported: the policy is a {type(policy).__name__}, not a DepthGRUModel", flush=True)
        print(f"[train] {'interrupted' if interrupted else 'finished'} at iteration {it}: {run_dir}", flush=True)
    if interrupted:
        raise SystemExit(128 + int(stop.signum or signal.SIGINT))
    return run_dir


# ------------------------------------------------------------------------------------------------ CLI


def build_parser() -> argparse.ArgumentParser:
    """The ``train.py`` argument parser."""
    p = argparse.ArgumentParser(prog="train.py", description="Train the depth CNN+GRU policy with rsl-rl PPO.")
    p.add_argument("--config", help="configs/train/<name>.yaml (required unless --resume)")
    p.add_argument("--set", nargs="+", action="extend", default=[], metavar="A.B=V",
                   help="dotted overrides, e.g. env.num_envs=32 (repeatable; all apply, in order)")  # fmt: skip
    p.add_argument("--num-envs", type=int, help="shorthand for --set env.num_envs=N")
    p.add_argument("--max-iterations", type=int, help="total iterations of the run")
    p.add_argument("--seed", type=int, help="sets seed and env.seed")
    p.add_argument("--device", help="cpu | cuda | cuda:i")
    p.add_argument("--log-dir", help="root of the run folders (default: logs)")
    p.add_argument("--resume", help="model_<it>.pt to continue (its run folder and stored config are reused)")
    return p


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """Resolve the config: (stored config of --resume | --config) + --set + shorthand flags."""
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
    if args.resume is not None:
        check_checkpoint(args.resume, "--resume")
        if args.config is not None:
            print(f"[train] --resume: using the run's stored config; ignoring --config {args.config}", flush=True)
        stored = read_checkpoint_infos(args.resume)["config"]
        cfg = load_train_config(overrides=overrides, base=load_train_config(overrides=stored))
        # The stored config is what ran; only the keys given now are checked against the algorithm.
        given = [o.split("=", 1)[0].removeprefix("runner.algorithm.") for o in overrides
                 if o.startswith("runner.algorithm.")]  # fmt: skip
        check_algorithm_keys(cfg, given)
        return cfg
    if args.config is None:
        raise ConfigError("--config is required (or --resume)")
    cfg = load_train_config(files=args.config, overrides=overrides)
    check_algorithm_keys(cfg)
    if cfg.runner.algorithm.lr_schedule_iterations == 0:
        # Frozen into the stored config, so a resume that extends --max-iterations keeps the schedule it started.
        cfg.runner.algorithm.lr_schedule_iterations = cfg.max_iterations
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    """``python train.py ...``: parse, resolve the config (failing fast on bad keys), train."""
    args = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(args)
        check_files(cfg, args.resume)
    except (ConfigError, ValueError) as err:
        print(f"train.py: error: {err}", file=sys.stderr)
        return 2
    train(cfg, resume=args.resume)
    return 0
