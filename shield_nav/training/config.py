"""The typed training config (:class:`TrainConfig`), its checks, and its translation into rsl-rl's dict."""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from envs.config import ConfigError, load_config, require, select_raw
from envs.navigation import NavConfig
from shield_nav.algorithms import ANCHOR_TARGETS
from shield_nav.algorithms.baselines import EXPERTS, BaselineConfig, OracleConfig
from shield_nav.safety.shield import ShieldConfig

CHECKPOINT_FORMAT_VERSION = 2
"""Version of the ``infos`` layout inside ``model_<it>.pt``; bump it and add a migration when it changes."""

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


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
    """The actor model (rsl-rl ``actor`` dict); its keys are :class:`~shield_nav.policies.models.DepthGRUModel`'s."""

    class_name: str = "shield_nav.policies.models:DepthGRUModel"
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
    ``algorithm.class_name: "shield_nav.algorithms.distillation:MultiHypothesisDistillation"`` (docs/training.md)."""
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
    """Keys every learning algorithm takes: the common part of ``runner.algorithm``.

    ``runner.algorithm`` is typed by its ``class_name`` (as Isaac Lab's ``RslRlPpoAlgorithmCfg`` and
    ``RslRlDistillationAlgorithmCfg``): :class:`PPOConfig`, :class:`AnchoredPPOConfig`, :class:`DistillationConfig`,
    :class:`ScheduledDistillationConfig` or :class:`MultiHypothesisDistillationConfig` (``ALGORITHM_CONFIGS``). A key
    the chosen class does not define is an unknown key: the config fails to load, naming it.
    """

    class_name: str = "PPO"
    """Algorithm class: ``PPO`` or ``shield_nav.algorithms.anchored:AnchoredPPO``; with ``runner.class_name:
    DistillationRunner`` rsl-rl's ``Distillation``, ``shield_nav.algorithms.distillation:ScheduledDistillation`` or, for
    a student with ``actor.num_hypotheses > 1``, ``shield_nav.algorithms.distillation:MultiHypothesisDistillation``."""
    num_learning_epochs: int = 4
    """Passes over each rollout."""
    learning_rate: float = 3.0e-4
    """Initial Adam learning rate (PPO: adapted by the KL schedule; distillation: see ``lr_schedule``)."""
    max_grad_norm: float = 1.0
    """Gradient clipping norm."""


@dataclass
class PPOConfig(AlgorithmConfig):
    """rsl-rl's ``PPO``."""

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
    use_clipped_value_loss: bool = True
    """Clip the value update like the policy ratio."""
    schedule: str = "adaptive"
    """``adaptive`` (learning rate follows desired_kl) or ``fixed``."""
    desired_kl: float = 0.01
    """Target KL for the adaptive schedule."""
    normalize_advantage_per_mini_batch: bool = False
    """Normalise advantages per mini-batch instead of over the whole rollout."""


@dataclass
class AnchoredPPOConfig(PPOConfig):
    """``shield_nav.algorithms.anchored:AnchoredPPO``: PPO plus a term holding the actor near a reference."""

    class_name: str = "shield_nav.algorithms.anchored:AnchoredPPO"
    """See :class:`AlgorithmConfig`."""
    anchor_coef: float = 0.0
    """Weight of the anchor term, the distance of the actor's mean action from the reference's on the same states
    (PPO fine-tuning)."""
    anchor_target: str = "actor_init"
    """The reference. ``actor_init``: the frozen ``runner.actor_init`` actor, ``mean((mu - mu_ref)^2)``. ``expert``:
    the scripted expert of ``runner.expert`` (kickstarting), DAgger's loss (``wta_loss`` with ``wta_epsilon`` and
    ``selection_coef`` for a multi-hypothesis actor)."""
    wta_epsilon: float = 0.05
    """Kickstarting a multi-hypothesis actor: share of the loss spread over the losing candidates, in [0, 1)."""
    selection_coef: float = 0.1
    """Kickstarting a multi-hypothesis actor: weight of the cross-entropy that trains the candidate scores."""


@dataclass
class DistillationConfig(AlgorithmConfig):
    """rsl-rl's ``Distillation`` (DAgger: the student imitates the teacher on the student's own states)."""

    class_name: str = "Distillation"
    """See :class:`AlgorithmConfig`."""
    gradient_length: int = 24
    """Steps of behaviour-cloning loss accumulated per gradient step (the student's BPTT window)."""
    loss_type: str = "mse"
    """``mse`` or ``huber`` between the student's mean action and the teacher's."""


@dataclass
class ScheduledDistillationConfig(DistillationConfig):
    """``ScheduledDistillation`` (:mod:`shield_nav.algorithms.distillation`): a rate schedule and rollout replay."""

    class_name: str = "shield_nav.algorithms.distillation:ScheduledDistillation"
    """See :class:`AlgorithmConfig`."""
    lr_schedule: str = "constant"
    """``constant`` (rsl-rl's) or ``cosine`` from ``learning_rate`` to ``lr_final`` over ``lr_schedule_iterations``
    updates."""
    lr_final: float = 1.0e-5
    """With ``lr_schedule: cosine``: the rate the cosine ends at."""
    lr_schedule_iterations: int = 0
    """With ``lr_schedule: cosine``: iterations the cosine takes; 0 = the run's ``max_iterations``."""
    replay_rollouts: int = 0
    """Past rollouts kept for replay (dataset aggregation); 0 = rsl-rl's fit-once DAgger. Each costs ``num_envs x
    num_steps_per_env`` observations of memory (128 x 24 depth images = 74 MB)."""
    replay_passes: int = 0
    """With replay: kept rollouts fitted per update (each costs about one learning epoch)."""


@dataclass
class MultiHypothesisDistillationConfig(ScheduledDistillationConfig):
    """``shield_nav.algorithms.distillation:MultiHypothesisDistillation``: the winner-takes-all loss.

    For students with ``actor.num_hypotheses > 1``.
    """

    class_name: str = "shield_nav.algorithms.distillation:MultiHypothesisDistillation"
    """See :class:`AlgorithmConfig`."""
    wta_epsilon: float = 0.05
    """Share of the loss spread over the losing candidates, in [0, 1)."""
    selection_coef: float = 0.1
    """Weight of the cross-entropy that trains the candidate scores."""


MULTI_HYPOTHESIS_ALGORITHM = "shield_nav.algorithms.distillation:MultiHypothesisDistillation"
"""``runner.algorithm.class_name`` of a student with ``actor.num_hypotheses > 1``."""
SCHEDULED_ALGORITHM = "shield_nav.algorithms.distillation:ScheduledDistillation"
"""``runner.algorithm.class_name`` of a single-head student with a learning-rate schedule."""
ANCHORED_ALGORITHM = "shield_nav.algorithms.anchored:AnchoredPPO"
"""``runner.algorithm.class_name`` of PPO fine-tuning anchored to its ``runner.actor_init`` actor."""
ALGORITHM_CONFIGS: dict[str, type[AlgorithmConfig]] = {
    "PPO": PPOConfig,
    ANCHORED_ALGORITHM: AnchoredPPOConfig,
    "Distillation": DistillationConfig,
    SCHEDULED_ALGORITHM: ScheduledDistillationConfig,
    MULTI_HYPOTHESIS_ALGORITHM: MultiHypothesisDistillationConfig,
}
"""The typed section of ``runner.algorithm`` for each ``class_name``."""


def _default_expert_params() -> BaselineConfig:
    return BaselineConfig(oracle=OracleConfig(episode_goal=True))


@dataclass
class ExpertConfig:
    """A scripted privileged expert: the teacher of oracle DAgger, or the reference of kickstarting PPO."""

    kind: str = ""
    """``oracle``: the geodesic-descent oracle of :mod:`shield_nav.algorithms.baselines` labels every state the student
    visits (with ``teacher.class_name: "shield_nav.policies.models:ExpertTeacher"`` and ``obs_groups.teacher:
    [expert]``); no ``teacher_checkpoint`` is needed; with ``AnchoredPPO`` and ``algorithm.anchor_target: expert``, the
    actions the PPO actor is held near. Empty: the trained teacher of ``teacher_checkpoint``."""
    params: BaselineConfig = field(default_factory=_default_expert_params)
    """The expert's parameters (:class:`shield_nav.algorithms.baselines.BaselineConfig`; ``oracle.episode_goal``
    defaults to true here: descend the field of the episode's goal point)."""
    flown_share: float = 0.0
    """DAgger's mixing share (Ross et al. 2011's beta), in [0, 1]: each env is drawn at every episode start, with
    this probability, to fly the episode on the expert's labels instead of the student's actions, which keeps the
    visited states near the expert's while the student is far from it; every state is labelled and learned either
    way. 0 (default): the student flies every episode (plain DAgger, as the shipped students were trained)."""


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
    algorithm: AlgorithmConfig = field(default_factory=PPOConfig)
    """The learning algorithm, typed by its ``class_name`` (``ALGORITHM_CONFIGS``)."""
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
    a distillation checkpoint's ``student_state_dict`` (e.g. ``checkpoints/student/model.pt``) or a PPO
    checkpoint's ``actor_state_dict``, with its observation normaliser and action std, and its stored curriculum
    levels when the env count matches. The critic, optimizer and iteration count start fresh."""
    critic_warmup_iterations: int = 0
    """PPO only: for the first this many iterations of a new run the actor's parameters are frozen, so the fresh
    critic learns the values of the loaded actor before its advantages move the policy (needs
    ``algorithm.schedule: fixed``: with a frozen actor the KL is 0 and the adaptive rule would raise the rate)."""
    average_iterations: int = 0
    """PPO only: if > 0, the run's final checkpoint and export hold the uniform average of the actor's weights after
    each of its last this many iterations (stochastic weight averaging, Izmailov et al. 2018), not the last
    iteration's weights alone, which are kept as ``snapshot_<it>.pt``. The running average travels in every
    checkpoint, so ``--resume`` continues it. 0: the last iteration's weights (rsl-rl's behaviour). See
    docs/training.md, "Weight averaging"."""
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
    env_shards: int = 1
    """Worker processes that step the envs (:class:`envs.sharded.ShardedVecEnv`): each builds and steps
    ``env.num_envs / env_shards`` of them with ``env.seed + k``, in parallel, and the learner sees one batch. 1: one
    process, the shipped recipes' setting (a sharded run draws its episodes from K seeds, so it does not repeat the
    unsharded run of the same seed). Raises collection throughput on machines with more cores than the env's
    threaded parts use (docs/training.md, "Hardware and throughput")."""
    env: NavConfig = field(default_factory=NavConfig)
    """The task (``envs.navigation.NavConfig``)."""
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    """The learner."""
    shield_in_loop: bool = False
    """Fly every training step's command through the HOCBF shield (``shield``), so the learner trains the deployed
    system, policy behind the shield: PPO's environment includes the shield, and a DAgger student visits the states
    of the shielded flight, which its expert labels (:mod:`shield_nav.training.shield_loop`). False: the policy alone
    (the paper's training)."""
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    """The shield of ``shield_in_loop`` (:class:`~shield_nav.safety.shield.ShieldConfig`; the evaluation's defaults)."""
    shield_penalty: float = 0.0
    """Intervention penalty of ``shield_in_loop``: each step's reward loses this times the shield's correction
    ``|a_safe - a_raw|`` [1 per m/s^2] (logged as ``reward/shield``), so the policy is paid for flying what the
    shield lets through unchanged rather than for leaning on it. 0: off (the shipped Full)."""
    view_penalty: float = 0.0
    """Look-where-you-fly penalty: each step's reward loses this times how far [rad] the horizontal velocity points
    outside the camera's horizontal view (0 within half the field of view of the heading), faded in from 0.5 to
    1.5 m/s of horizontal speed (logged as ``reward/view``). A vehicle that slides sideways moves into space its
    depth image does not show. 0: off (every recipe)."""

    def validate(self, prefix: str = "") -> None:
        """Cross-field checks naming the key."""
        require(self.max_iterations >= 1, f"{prefix}max_iterations", f"must be >= 1, got {self.max_iterations}")
        require(self.num_threads >= 0, f"{prefix}num_threads", "must be >= 0")
        require(self.env_shards >= 1, f"{prefix}env_shards", f"must be >= 1, got {self.env_shards}")
        require(self.env.num_envs % self.env_shards == 0, f"{prefix}env_shards",
                f"{self.env_shards} must divide env.num_envs ({self.env.num_envs})")  # fmt: skip
        require(
            self.device == "cpu" or self.device.startswith("cuda"),
            f"{prefix}device",
            f"must be 'cpu' or 'cuda[:i]', got {self.device!r}",
        )
        r = self.runner
        self.shield.validate(f"{prefix}shield.")
        pen = self.shield_penalty
        require(math.isfinite(pen) and pen >= 0, f"{prefix}shield_penalty", f"must be a finite number >= 0, got {pen}")
        require(pen == 0 or self.shield_in_loop, f"{prefix}shield_penalty",
                f"{pen} needs shield_in_loop: true (it penalises the shield's corrections)")  # fmt: skip
        vp = self.view_penalty
        require(math.isfinite(vp) and vp >= 0, f"{prefix}view_penalty", f"must be a finite number >= 0, got {vp}")
        require(r.num_steps_per_env >= 1, f"{prefix}runner.num_steps_per_env", "must be >= 1")
        require(r.save_interval >= 1, f"{prefix}runner.save_interval", "must be >= 1")
        runners = ("OnPolicyRunner", "DistillationRunner")
        require(
            r.class_name in runners, f"{prefix}runner.class_name", f"must be one of {runners}, got {r.class_name!r}"
        )
        a = r.algorithm
        distill = r.class_name == "DistillationRunner"
        multi = r.actor.num_hypotheses > 1
        algos = ("PPO", ANCHORED_ALGORITHM)
        if distill:
            algos = (MULTI_HYPOTHESIS_ALGORITHM,) if multi else ("Distillation", SCHEDULED_ALGORITHM)
        got = a.class_name
        require(r.actor.num_hypotheses >= 1, f"{prefix}runner.actor.num_hypotheses", "must be >= 1")
        require(distill or not multi or r.actor_init, f"{prefix}runner.actor.num_hypotheses",
                "> 1 only with DistillationRunner or PPO fine-tuning from runner.actor_init")  # fmt: skip
        require(got in algos, f"{prefix}runner.algorithm.class_name",
                f"must be one of {algos} with runner.class_name {r.class_name!r} and actor.num_hypotheses "
                f"{r.actor.num_hypotheses}, got {got!r}")  # fmt: skip
        require(a.num_learning_epochs >= 1, f"{prefix}runner.algorithm.num_learning_epochs", "must be >= 1")
        require(a.learning_rate >= 0.0, f"{prefix}runner.algorithm.learning_rate", "must be >= 0")
        kickstart = False
        if isinstance(a, PPOConfig):
            mb = a.num_mini_batches
            require(mb >= 1 and self.env.num_envs % mb == 0, f"{prefix}runner.algorithm.num_mini_batches",
                    f"must divide env.num_envs ({self.env.num_envs}) for the recurrent generator, "
                    f"got {mb}")  # fmt: skip
            require(a.schedule in ("adaptive", "fixed"), f"{prefix}runner.algorithm.schedule", "adaptive|fixed")
        if isinstance(a, AnchoredPPOConfig):
            require(a.anchor_coef >= 0.0, f"{prefix}runner.algorithm.anchor_coef", f"must be >= 0, got {a.anchor_coef}")
            require(bool(r.actor_init), f"{prefix}runner.actor_init",
                    f"is required by {ANCHORED_ALGORITHM!r}: it is the actor the fine-tuning starts from")  # fmt: skip
            require(a.anchor_target in ANCHOR_TARGETS, f"{prefix}runner.algorithm.anchor_target",
                    f"must be one of {ANCHOR_TARGETS}, got {a.anchor_target!r}")  # fmt: skip
            kickstart = a.anchor_target == "expert"
            require(
                not kickstart or r.expert.kind,
                f"{prefix}runner.expert.kind",
                "must be set with runner.algorithm.anchor_target 'expert' (the expert the actor is held near)",
            )
        if isinstance(a, (AnchoredPPOConfig, MultiHypothesisDistillationConfig)):
            require(0.0 <= a.wta_epsilon < 1.0, f"{prefix}runner.algorithm.wta_epsilon", "must be in [0, 1)")
            require(a.selection_coef >= 0.0, f"{prefix}runner.algorithm.selection_coef", "must be >= 0")
        if isinstance(a, DistillationConfig):
            require(a.loss_type in ("mse", "huber"), f"{prefix}runner.algorithm.loss_type", "mse|huber")
            require(a.gradient_length >= 1, f"{prefix}runner.algorithm.gradient_length", "must be >= 1")
        if isinstance(a, ScheduledDistillationConfig):
            require(a.lr_schedule in ("constant", "cosine"), f"{prefix}runner.algorithm.lr_schedule",
                    f"must be 'constant' or 'cosine', got {a.lr_schedule!r}")  # fmt: skip
            require(a.lr_schedule == "constant" or 0.0 < a.lr_final <= a.learning_rate,
                    f"{prefix}runner.algorithm.lr_final",
                    f"must be in (0, runner.algorithm.learning_rate = {a.learning_rate}], "
                    f"got {a.lr_final}")  # fmt: skip
            require(a.lr_schedule_iterations >= 0, f"{prefix}runner.algorithm.lr_schedule_iterations",
                    "must be >= 0 (0 = max_iterations)")  # fmt: skip
            rr, rp = a.replay_rollouts, a.replay_passes
            require(rr >= 0 and 0 <= rp <= rr and (rr > 0) == (rp > 0), f"{prefix}runner.algorithm.replay_passes",
                    f"needs 0 <= replay_passes <= replay_rollouts, both 0 or both > 0; got {rp} and {rr}")  # fmt: skip
        require(distill or not r.student_init, f"{prefix}runner.student_init", "only with DistillationRunner")
        require(not distill or not r.actor_init, f"{prefix}runner.actor_init", "only with OnPolicyRunner (PPO)")
        require(r.critic_warmup_iterations >= 0, f"{prefix}runner.critic_warmup_iterations", "must be >= 0")
        require(r.critic_warmup_iterations == 0 or (isinstance(a, PPOConfig) and a.schedule == "fixed"),
                f"{prefix}runner.critic_warmup_iterations",
                "needs runner.class_name OnPolicyRunner and runner.algorithm.schedule 'fixed'")  # fmt: skip
        n_avg = r.average_iterations
        require(n_avg == 0 or not distill, f"{prefix}runner.average_iterations",
                "only with runner.class_name OnPolicyRunner (PPO)")  # fmt: skip
        require(0 <= n_avg <= self.max_iterations - r.critic_warmup_iterations, f"{prefix}runner.average_iterations",
                f"must be in [0, max_iterations - runner.critic_warmup_iterations = "
                f"{self.max_iterations - r.critic_warmup_iterations}] (the iterations the actor trains), "
                f"got {n_avg}")  # fmt: skip
        for key in ("student", "teacher") if distill else ("actor", "critic"):
            require(key in r.obs_groups, f"{prefix}runner.obs_groups.{key}", "is required")
        uses_expert_obs = any("expert" in groups for groups in r.obs_groups.values())
        require(not uses_expert_obs or r.expert.kind, f"{prefix}runner.expert.kind",
                "must be set when an obs group reads the 'expert' observation")  # fmt: skip
        if r.expert.kind:
            require(r.expert.kind in EXPERTS, f"{prefix}runner.expert.kind",
                    f"unknown expert {r.expert.kind!r}; known: {sorted(EXPERTS)}")  # fmt: skip
            require(
                distill or kickstart,
                f"{prefix}runner.expert.kind",
                "only with runner.class_name DistillationRunner, or AnchoredPPO with anchor_target 'expert'",
            )
            require(not distill or r.obs_groups.get("teacher") == ["expert"], f"{prefix}runner.obs_groups.teacher",
                    f"must be [expert] with runner.expert.kind {r.expert.kind!r}")  # fmt: skip
            require(not distill or r.teacher.class_name.endswith("ExpertTeacher"), f"{prefix}runner.teacher.class_name",
                    "must be 'shield_nav.policies.models:ExpertTeacher' with a scripted expert")  # fmt: skip
        share = r.expert.flown_share
        require(isinstance(share, (int, float)) and math.isfinite(share) and 0 <= share <= 1,
                f"{prefix}runner.expert.flown_share", f"must be in [0, 1], got {share!r}")  # fmt: skip
        require(share == 0 or (distill and r.expert.kind), f"{prefix}runner.expert.flown_share",
                "only with runner.class_name DistillationRunner and a scripted runner.expert.kind")  # fmt: skip
        uses_teacher_obs = any("teacher" in groups for groups in r.obs_groups.values())
        require(not uses_teacher_obs or self.env.local_map.enabled, f"{prefix}env.local_map.enabled",
                "must be true when an obs group reads the 'teacher' observation")  # fmt: skip


def load_train_config(
    files: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    overrides: Sequence[str] | dict | None = None,
    base: TrainConfig | None = None,
) -> TrainConfig:
    """Load a :class:`TrainConfig` from YAML file(s) (with ``defaults:`` includes) and dotted overrides.

    ``runner.algorithm`` takes the typed section of its ``class_name`` (``ALGORITHM_CONFIGS``), read from the same
    layers first; a key that section does not define is an unknown key.

    Raises:
        ConfigError: Naming the dotted key of the first unknown key or bad value, before any work.
    """
    if files is not None and not isinstance(files, (str, os.PathLike)):
        files = list(files)
    base = TrainConfig() if base is None else base
    name = select_raw("runner.algorithm.class_name", files, overrides, default=base.runner.algorithm.class_name)
    if (new := moved_class_path(name)) is not None:
        raise ConfigError(f"config key 'runner.algorithm.class_name': {name!r} names a module that moved; use {new!r}")
    if name not in ALGORITHM_CONFIGS:
        raise ConfigError(f"config key 'runner.algorithm.class_name': unknown algorithm {name!r}; known: "
                          f"{sorted(ALGORITHM_CONFIGS)}")  # fmt: skip
    schema = ALGORITHM_CONFIGS[name]
    if type(base.runner.algorithm) is not schema:
        # Start the section from the new class's defaults, keeping the values of the keys both classes define.
        old = base.runner.algorithm
        shared = {f.name: getattr(old, f.name) for f in dataclasses.fields(schema)
                  if f.name != "class_name" and hasattr(old, f.name)}  # fmt: skip
        base = copy.deepcopy(base)
        base.runner.algorithm = schema(**shared)
    cfg = load_config(TrainConfig, files=files, overrides=overrides, base=base)
    _refuse_moved_class_paths(cfg)
    return cfg


MOVED_MODULES = {
    "shield_nav.models": "shield_nav.policies.models",
    "shield_nav.anchored": "shield_nav.algorithms.anchored",
    "shield_nav.distillation": "shield_nav.algorithms.distillation",
}
"""Modules whose classes configs name by path (``module:Class``), moved when the package was laid out by role on
2026-12-06: old path -> new path."""


def moved_class_path(value: Any) -> str | None:
    """The current path of a ``module:Class`` string that names a moved module, else None."""
    if isinstance(value, str) and ":" in value:
        module, _, name = value.partition(":")
        if module in MOVED_MODULES:
            return f"{MOVED_MODULES[module]}:{name}"
    return None


def migrate_class_paths(config: Any) -> Any:
    """A stored config (a checkpoint's, a pipeline record's) with every moved ``module:Class`` path made current.

    The classes are the same; only their modules moved (:data:`MOVED_MODULES`). Returns a new object.
    """
    if isinstance(config, dict):
        return {k: migrate_class_paths(v) for k, v in config.items()}
    if isinstance(config, list):
        return [migrate_class_paths(v) for v in config]
    return moved_class_path(config) or config


def _refuse_moved_class_paths(cfg: TrainConfig) -> None:
    """A config written by hand that names a moved module: an error naming the key and the current path."""

    def walk(node: Any, key: str) -> None:
        if dataclasses.is_dataclass(node):
            for f in dataclasses.fields(node):
                walk(getattr(node, f.name), f"{key}.{f.name}" if key else f.name)
        elif isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{key}.{k}")
        elif (new := moved_class_path(node)) is not None:
            raise ConfigError(f"config key '{key}': {node!r} names a module that moved; use {new!r}")

    walk(cfg, "")


def migrate_flat_algorithm(config: dict, source: str = "stored config") -> dict:
    """A stored config of checkpoint format 1 in the typed layout of format 2.

    Format 1 stored one flat ``runner.algorithm`` with every algorithm's keys. The keys its class's section does not
    define are dropped, which is what the runner did with them when it trained. A dropped key whose value was not
    the flat default is named in a warning (it had no effect on that run, but whoever set it may have thought it
    did).
    """
    out = copy.deepcopy(config)
    algo = (out.get("runner") or {}).get("algorithm")
    if not isinstance(algo, dict):
        return out
    schema = ALGORITHM_CONFIGS.get(algo.get("class_name", "PPO"))
    if schema is None:
        return out  # load_train_config names the unknown class
    known = {f.name for f in dataclasses.fields(schema)}
    flat = {f.name: f.default for cls in ALGORITHM_CONFIGS.values() for f in dataclasses.fields(cls)}
    # Format 1's train.py wrote max_iterations into lr_schedule_iterations for every algorithm, not only by choice.
    flat["lr_schedule_iterations"] = (flat["lr_schedule_iterations"], out.get("max_iterations"))
    for key in [k for k in algo if k not in known]:
        value = algo.pop(key)
        expected = flat.get(key)
        if key in flat and value not in (expected if isinstance(expected, tuple) else (expected,)):
            warnings.warn(f"{source}: runner.algorithm.{key} = {value!r} was not taken by {algo.get('class_name')!r} "
                          "when this run trained; dropped", stacklevel=2)  # fmt: skip
    return out
