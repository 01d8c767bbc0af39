"""A training run: runners with versioned checkpoints, the env, run folders, resume, signals, exports.

The command line is :mod:`~shield_nav.training.cli`; the checks run before training, :mod:`~shield_nav.training.checks`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import functools
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

import torch
from rsl_rl.env import VecEnv
from rsl_rl.runners import DistillationRunner, OnPolicyRunner

from envs.config import ConfigError, to_dict, to_yaml
from shield_nav.algorithms.baselines import EXPERTS
from shield_nav.provenance import cpu_model, cpu_simd, package_versions
from shield_nav.training.checks import check_files, in_run_folder
from shield_nav.training.config import CHECKPOINT_FORMAT_VERSION, REPO_ROOT, TrainConfig
from shield_nav.training.rsl_rl_cfg import rsl_rl_train_cfg


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
            "packages": package_versions(),
            "cpu_model": cpu_model(),
            "cpu_simd": cpu_simd(),  # torch, oneDNN and MKL pick kernels by it: another kind trains other bits
            "cpu_kernels": torch.backends.cpu.get_cpu_capability(),
            "saved_at": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        if hasattr(self.env, "curriculum_levels"):
            full["curriculum_levels"] = self.env.curriculum_levels  # restored by --resume
        average = getattr(self, "weight_average", None)
        if average is not None:
            full["weight_average"] = average.state()  # continued by --resume
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
    """The rsl-rl VecEnv of the task (CPU, numpy inside; tensors on the learner device).

    With ``env_shards`` K > 1, K worker processes each step :func:`shard_env` ``(cfg, k)``
    (:class:`envs.sharded.ShardedVecEnv`).
    """
    if cfg.env_shards > 1:
        from envs.sharded import ShardedVecEnv

        factories = [functools.partial(shard_env, cfg, k) for k in range(cfg.env_shards)]
        return ShardedVecEnv(factories, device=cfg.device, cfg=cfg.env)
    return _single_env(cfg)


def shard_env(cfg: TrainConfig, k: int) -> VecEnv:
    """Shard ``k`` of a sharded run: the unsharded env of ``num_envs / env_shards`` envs and ``env.seed + k`` (CPU)."""
    env_cfg = dataclasses.replace(cfg.env, num_envs=cfg.env.num_envs // cfg.env_shards, seed=cfg.env.seed + k)
    return _single_env(dataclasses.replace(cfg, env=env_cfg, env_shards=1, device="cpu"))


def _single_env(cfg: TrainConfig) -> VecEnv:
    from envs.navigation import NavigationEnv
    from envs.rsl_rl import RslRlVecEnv

    expert = None
    if cfg.runner.expert.kind:
        expert = EXPERTS[cfg.runner.expert.kind](cfg.runner.expert.params)
    command_filter = None
    if cfg.shield_in_loop:
        from shield_nav.training.shield_loop import ShieldInLoop

        command_filter = ShieldInLoop(cfg.shield, cfg.env.camera)
    return RslRlVecEnv(NavigationEnv(config=cfg.env), device=cfg.device, expert=expert, command_filter=command_filter,
                       filter_penalty=cfg.shield_penalty, view_penalty=cfg.view_penalty,
                       expert_flown_share=cfg.runner.expert.flown_share)  # fmt: skip


def _randomize_episode_lengths(env: VecEnv) -> None:
    """Start each env at a uniform random time of its episode (rsl-rl's ``init_at_random_ep_len``).

    Done here because rsl-rl's runner calls ``int(env.max_episode_length)``, which fails for the task's
    per-env limits (N,); this draws ``episode_length_buf[i] ~ U{0, ..., max_episode_length[i] - 1}``.
    """
    limit = torch.as_tensor(env.max_episode_length, dtype=torch.float32).expand(env.num_envs)
    env.episode_length_buf = (torch.rand(env.num_envs) * limit).long()


def new_stamped_dir(cfg: TrainConfig, name: str) -> str:
    """A fresh ``<log_root>/<experiment>/<stamp>_<name>`` folder, claimed atomically.

    Runs of the same config started within the same second (e.g. several seeds launched together) would otherwise
    share one folder and overwrite each other's checkpoints: the second and later get ``_2``, ``_3``, ...
    """
    stamp = datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    base = os.path.join(cfg.log_root, cfg.experiment_name, f"{stamp}_{name}")
    os.makedirs(os.path.dirname(base), exist_ok=True)
    path, k = base, 1
    while True:
        try:
            os.mkdir(path)  # fails if another run claimed it first
            break
        except FileExistsError:
            k += 1
            path = f"{base}_{k}"
    return path


def _new_run_dir(cfg: TrainConfig) -> str:
    """A fresh run folder for ``cfg`` (:func:`new_stamped_dir`) with its ``params/`` subfolder."""
    path = new_stamped_dir(cfg, cfg.name)
    os.makedirs(os.path.join(path, "params"), exist_ok=True)
    return path


def _write_export_source(run_dir: str, it: int) -> None:
    """Record which checkpoint ``exported/`` was made from: ``exported/source.json`` (file name, iteration, sha256).

    ``network: fixed_order`` reads it to fly that checkpoint when the folder's TorchScript ``policy.pt`` is gone
    (:func:`shield_nav.evaluation.policies.load_policy`). Without the checkpoint on disk an earlier record is removed,
    so it never names another checkpoint than the one exported.
    """
    from shield_nav.evaluation.policies import EXPORT_SOURCE_FILE, _sha256
    from shield_nav.jsonio import write_json

    ckpt = os.path.join(run_dir, f"model_{it}.pt")
    record = os.path.join(run_dir, "exported", EXPORT_SOURCE_FILE)
    if os.path.isfile(ckpt):
        write_json(record, {"checkpoint": os.path.basename(ckpt), "iteration": it, "sha256": _sha256(ckpt)})
    elif os.path.isfile(record):
        os.remove(record)


def _init_student(runner: Any, path: str, device: str) -> dict:
    """Load a checkpoint's student weights into the runner's student; return the checkpoint's ``infos``.

    A single-head student initialises a multi-hypothesis one: every candidate starts as its head
    (:func:`shield_nav.policies.models.expand_single_head`), so training starts from the single-head policy. A student
    whose state has more values (a new observation group after ``state``, e.g. ``memory``) starts from one with fewer
    through zero weights on the new values (:func:`shield_nav.policies.models.expand_state_inputs`).
    """
    from shield_nav.policies.models import expand_single_head

    student = runner.alg._raw_student
    ckpt = torch.load(path, map_location=device, weights_only=False)
    weights = ckpt.get("student_state_dict")
    if weights is None:
        raise ConfigError(f"config key 'runner.student_init': {path!r} holds no student (not a distillation run)")
    single = not any(key.startswith("mlp.0.0.") for key in weights)
    if getattr(student, "num_hypotheses", 1) > 1 and single:
        weights = expand_single_head(weights, student)
        print(f"[train] single-head student expanded to {student.num_hypotheses} hypotheses", flush=True)
    student.load_state_dict(_widened(weights, student, "student"))
    return ckpt.get("infos") or {}


def expert_changes(before: dict | None, after: dict) -> list[str]:
    """The settings of ``runner.expert`` (kind and params) in which ``after`` differs from ``before``, as lines.

    ``before`` is the ``runner.expert`` section of the config an initial policy was trained with (its checkpoint's
    ``infos["config"]``), ``after`` this run's. Only keys both configs hold are compared: a key added to the code
    after the initial policy was trained is not in its config (new keys default to the behaviour before them).
    DAgger's mixing share is not a teacher setting and is left out. An initial policy trained without a scripted
    expert gives no lines. Each line reads ``params.expert.tracker: 'tangent' -> 'mppi'``.
    """
    if not before or not before.get("kind"):
        return []

    def flat(section: Any, prefix: str = "") -> dict[str, Any]:
        if not isinstance(section, dict):
            return {prefix[:-1]: section}
        out: dict[str, Any] = {}
        for key, value in section.items():
            out.update(flat(value, f"{prefix}{key}."))
        return out

    old, new = (
        flat({k: v for k, v in before.items() if k != "flown_share"}),
        flat({k: v for k, v in after.items() if k != "flown_share"}),
    )
    return [f"{key}: {old[key]!r} -> {new[key]!r}" for key in sorted(old.keys() & new.keys()) if old[key] != new[key]]


def _note_expert_switch(cfg: TrainConfig, path: str, infos: dict, key: str) -> None:
    """Print which expert settings differ from the ones the initial policy at ``path`` was trained with.

    A student distilled from one tracker and fine-tuned on another's labels can come apart (docs/training.md,
    "Expert DAgger"), so a run that switches says so before it trains. Information only: recipes switch on purpose
    (the oracle student's first expert cycle).
    """
    if not cfg.runner.expert.kind:
        return
    before = ((infos.get("config") or {}).get("runner") or {}).get("expert")
    changes = expert_changes(before, to_dict(cfg.runner.expert))
    if changes:
        shown = "; ".join(changes[:8]) + (f"; and {len(changes) - 8} more" if len(changes) > 8 else "")
        print(f"[train] note: runner.expert differs from the expert the policy of '{key}' ({path}) was trained "
              f"with: {shown}", flush=True)  # fmt: skip


def _widened(weights: dict, model: Any, what: str) -> dict:
    """``weights`` for ``model``, widened where the model is wider.

    A new group after ``state`` (e.g. ``memory`` or ``clock``) enters through zero weights
    (:func:`shield_nav.policies.models.expand_state_inputs`); a wider depth encoder (more channels or image features)
    keeps the old filters and reads its new ones through zero weights
    (:func:`shield_nav.policies.models.widen_encoder`). Either way the model acts as the one it starts from. Otherwise
    ``weights`` unchanged.
    """
    from shield_nav.policies.models import encoder_is_wider, encoder_widths, expand_state_inputs, widen_encoder

    mean = weights.get("obs_normalizer._mean")
    if mean is not None and hasattr(model, "obs_dim") and mean.shape[-1] < model.obs_dim:
        print(f"[train] {what} state widened from {mean.shape[-1]} to {model.obs_dim} values "
              f"(new inputs start at zero weight)", flush=True)  # fmt: skip
        weights = expand_state_inputs(weights, model)
    if hasattr(model, "encoder") and encoder_is_wider(weights, model):  # a wider checkpoint: _check_encoder_widths
        before, after = encoder_widths(weights), encoder_widths(model.state_dict())
        print(f"[train] {what} depth encoder widened from {before} to {after} channels / features "
              f"(new ones start at zero outgoing weight)", flush=True)  # fmt: skip
        weights = widen_encoder(weights, model)
    return weights


def _check_encoder_widths(cfg: TrainConfig, resume: str | os.PathLike | None) -> None:
    """Refuse a warm start whose depth encoder is wider than ``runner.actor``'s, before any folder or env is made.

    The widths are read from the checkpoint's convolution and projection weights: output channels per layer, then
    the image features. A narrower checkpoint is widened at load (:func:`_widened`); a wider one cannot be.
    """
    from shield_nav.policies.models import encoder_widths

    path = cfg.runner.student_init or cfg.runner.actor_init
    if resume is not None or not path or "cnn_channels" not in dataclasses.asdict(cfg.runner.actor):
        return
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    weights = ckpt.get("student_state_dict") or ckpt.get("actor_state_dict") or {}
    before = encoder_widths(weights)
    after = [*(int(c) for c in cfg.runner.actor.cnn_channels), int(cfg.runner.actor.cnn_feature_dim)]
    if len(before) == len(after) and any(b > a for b, a in zip(before, after, strict=True)):
        raise ConfigError(
            f"config key 'runner.actor.cnn_channels' / 'cnn_feature_dim': the depth encoder of {path} has "
            f"{before[:-1]} channels and {before[-1]} features, runner.actor {after[:-1]} and {after[-1]}; "
            f"set them to the checkpoint's (or wider)"
        )


def _restore_levels(env: Any, levels: list[int] | None, source: str, strict: bool = False) -> None:
    """Put the envs back on the curriculum levels a checkpoint stored (same env count only).

    ``strict`` (a resumed run): levels that do not fit the scene list raise. Otherwise (a student or actor taken
    from another run) they are used only where this env runs a curriculum and every level names one of its scenes,
    and a line says why they were not.
    """
    if levels is None or not hasattr(env, "set_curriculum_levels") or len(levels) != env.num_envs:
        return
    if not strict:
        if not env.curriculum_active:
            print(f"[train] curriculum off: the levels stored in {source} are not used", flush=True)
            return
        num_scenes = env.num_scenes
        if max(levels) >= num_scenes:
            print(
                f"[train] the levels stored in {source} reach {max(levels)}, beyond this scene list "
                f"(0..{num_scenes - 1}): not used",
                flush=True,
            )
            return
    env.set_curriculum_levels(levels)
    print(f"[train] curriculum levels restored (mean {sum(levels) / len(levels):.2f})", flush=True)


def _weight_average(runner: Any, cfg: TrainConfig, infos: dict, rank: int, start_it: int) -> Any:
    """The run's :class:`WeightAverage` (``runner.average_iterations`` > 0), restored from a resumed checkpoint.

    A run that resumes past iterations the average needs (its checkpoint was saved without them) is refused here,
    before any training.
    """
    n = cfg.runner.average_iterations
    if n <= 0 or rank != 0:
        return None
    from shield_nav.training.averaging import WeightAverage

    first, last = cfg.max_iterations - n, cfg.max_iterations - 1
    stored = infos.get("weight_average")
    if stored is not None and stored.get("applied"):
        print(f"[train] the checkpoint already holds the average of iterations {first}-{last}", flush=True)
        return None
    average = WeightAverage.from_state(stored, first, last) if stored is not None else WeightAverage(first, last)
    expected = average.iterations[-1] + 1 if average.iterations else first
    if start_it > expected:
        raise ConfigError(f"config key 'runner.average_iterations': the run resumes at iteration {start_it}, but the "
                          f"average of iterations {first}-{last} needs iteration {expected} on, which the resumed "
                          f"checkpoint does not hold (saved without runner.average_iterations = {n})")  # fmt: skip
    runner.weight_average = average  # read by _VersionedSave.save
    print(f"[train] weight averaging: the final actor is the mean of iterations {first}-{last}"
          f"{f' ({average.count} averaged so far)' if average.count else ''}", flush=True)  # fmt: skip
    return average


def _apply_weight_average(runner: Any, average: Any, run_dir: str, it: int) -> None:
    """Keep the last iteration as ``snapshot_<it>.pt``; write the averaged actor as the final ``model_<it>.pt``."""
    if not average.complete:
        raise RuntimeError(f"weight averaging: iterations {average.iterations[:1]}..{average.iterations[-1:]} of "
                           f"{average.first}-{average.last} were averaged; the run's final checkpoint is the last "
                           f"iteration's (model_{it}.pt)")  # fmt: skip
    final = os.path.join(run_dir, f"model_{it}.pt")
    runner.save(os.path.join(run_dir, f"snapshot_{it}.pt"))  # the last iteration's own weights, for the record
    actor = runner.alg._raw_actor
    actor.load_state_dict(average.averaged_state_dict(actor))
    runner.weight_average = None
    summary = {"first": average.first, "last": average.last, "count": average.count, "applied": True}
    runner.save(final, infos={"weight_average": summary})
    print(f"[train] weight averaging: model_{it}.pt holds the mean actor of iterations {average.first}-{average.last} "
          f"({average.count}); the last iteration's own weights are snapshot_{it}.pt", flush=True)  # fmt: skip


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
    run_dir: str | None = None,
) -> str:
    """Train (or resume) one run; return its folder.

    Args:
        cfg: The resolved config.
        resume: A ``model_<it>.pt`` to continue from: weights, optimizer, normalisers and the iteration count
            are restored, logging continues in the checkpoint's folder (tensorboard curves continue at ``it + 1``),
            and training runs until ``cfg.max_iterations`` iterations exist in total.
        env_factory: Builds the VecEnv from ``cfg`` (tests pass a small synthetic env).
        run_dir: The run folder to use instead of a new time-stamped one (a pipeline's stage folder); a ``resume``
            checkpoint inside it continues there.
    """
    rank = int(os.getenv("RANK", "0"))
    world = int(os.getenv("WORLD_SIZE", "1"))
    device = cfg.device
    if world > 1:  # torchrun: one process per GPU; rsl-rl's runner initialises NCCL and averages gradients
        if not device.startswith("cuda"):
            raise ConfigError("config key 'device': multi-process training (WORLD_SIZE > 1) needs 'cuda'")
        device = f"cuda:{int(os.getenv('LOCAL_RANK', '0'))}"
    check_files(cfg, resume)
    _check_encoder_widths(cfg, resume)
    threads = configure_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed + rank)
    print(f"[train] torch {torch.__version__}: {threads} intra-op thread(s), 1 inter-op; CPU kernels "
          f"{torch.backends.cpu.get_cpu_capability()}; device {device}", flush=True)  # fmt: skip

    if run_dir is not None:
        os.makedirs(run_dir, exist_ok=True)
    elif resume is not None and in_run_folder(resume):
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
    resumed_infos: dict = {}
    if cfg.runner.class_name == "DistillationRunner" and cfg.runner.expert.kind:
        runner.alg.teacher_loaded = True  # the scripted expert has no weights to load
        print(f"[train] teacher: the scripted '{cfg.runner.expert.kind}' expert (obs group 'expert')", flush=True)
    if cfg.runner.class_name == "DistillationRunner" and resume is None and not cfg.runner.expert.kind:
        runner.load(cfg.runner.teacher_checkpoint, map_location=device)  # actor weights -> teacher only
        print(f"[train] teacher loaded from {cfg.runner.teacher_checkpoint}", flush=True)
    if cfg.runner.class_name == "DistillationRunner" and resume is None and cfg.runner.student_init:
        infos = _init_student(runner, cfg.runner.student_init, device)
        print(f"[train] student initialised from {cfg.runner.student_init}", flush=True)
        _note_expert_switch(cfg, cfg.runner.student_init, infos, "runner.student_init")
        _restore_levels(env, infos.get("curriculum_levels"), cfg.runner.student_init)
    if cfg.runner.actor_init and resume is None:
        ckpt = torch.load(cfg.runner.actor_init, map_location=device, weights_only=False)
        weights = ckpt.get("student_state_dict") or ckpt.get("actor_state_dict")
        if weights is None:
            raise ConfigError(f"config key 'runner.actor_init': {cfg.runner.actor_init!r} holds no actor or student")
        runner.alg._raw_actor.load_state_dict(_widened(weights, runner.alg._raw_actor, "actor"))
        print(f"[train] actor initialised from {cfg.runner.actor_init}", flush=True)
        _note_expert_switch(cfg, cfg.runner.actor_init, ckpt.get("infos") or {}, "runner.actor_init")
        _restore_levels(env, (ckpt.get("infos") or {}).get("curriculum_levels"), cfg.runner.actor_init)
    if resume is not None:
        # DAgger from a scripted expert saved no teacher weights (an empty dict): load everything else. A PPO run
        # kickstarted by a scripted expert loads everything (its actor and critic are PPO's).
        scripted_teacher = cfg.runner.class_name == "DistillationRunner" and cfg.runner.expert.kind
        load_cfg = {"student": True, "optimizer": True, "iteration": True} if scripted_teacher else None
        infos = resumed_infos = runner.load(str(resume), load_cfg=load_cfg, map_location=device) or {}
        start_it = runner.current_learning_iteration + 1  # the checkpoint holds a finished iteration
        runner.current_learning_iteration = start_it
        runner.logger.tot_timesteps = int(infos.get("tot_timesteps", 0))
        runner.logger.tot_time = float(infos.get("tot_time", 0.0))
        _restore_levels(env, infos.get("curriculum_levels"), str(resume), strict=True)
        print(f"[train] resumed from {resume}: continuing at iteration {start_it}", flush=True)
    remaining = cfg.max_iterations - start_it
    average = _weight_average(runner, cfg, resumed_infos, rank, start_it)
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
        if average is not None:  # after the update, before rsl-rl's save of this iteration
            average.add(runner.alg._raw_actor, kwargs.get("it", runner.current_learning_iteration))
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
        if hasattr(env, "close"):  # a sharded env's worker processes
            env.close()

    if rank == 0:
        # The last finished iteration: with nothing left to train, the resumed checkpoint's own (not start_it, which
        # names no checkpoint: its export record would be dropped).
        it = runner.current_learning_iteration if remaining > 0 else start_it - 1
        if interrupted:
            runner.save(os.path.join(run_dir, f"model_{it}.pt"), infos={"interrupted": interrupted})
        elif average is not None:
            _apply_weight_average(runner, average, run_dir, it)
        runner.logger.stop_logging_writer()
        if runner.logger.writer is not None and hasattr(runner.logger.writer, "close"):
            runner.logger.writer.close()
        from shield_nav.policies.export import export_policy
        from shield_nav.policies.models import DepthGRUModel

        policy = runner.alg.get_policy()
        if isinstance(policy, DepthGRUModel):
            try:
                paths = export_policy(policy, os.path.join(run_dir, "exported"))
            except Exception:
                # The checkpoint is on disk. A known cause: TorchScript re-reads the model's source file, so editing
                # shield_nav/policies/models.py while a run trains can break the run's final export (not its weights).
                print(f"[train] the export failed; model_{it}.pt is saved. Re-export it with: python -m "
                      f"shield_nav.tools.package {os.path.join(run_dir, f'model_{it}.pt')} --name <policy name>",
                      file=sys.stderr, flush=True)  # fmt: skip
                raise
            _write_export_source(run_dir, it)
            print(f"[train] exported {paths['jit']} and {paths['onnx']}", flush=True)
        else:  # a privileged teacher: not deployable (it reads the local ESDF map), so nothing is exported
            print(f"[train] not exported: the policy is a {type(policy).__name__}, not a DepthGRUModel", flush=True)
        print(f"[train] {'interrupted' if interrupted else 'finished'} at iteration {it}: {run_dir}", flush=True)
    if interrupted:
        raise SystemExit(128 + int(stop.signum or signal.SIGINT))
    return run_dir
