"""Checks run before any training work: the device, the checkpoints and files a run needs, a checkpoint's infos.

Kept free of module-level torch and rsl-rl imports, so that ``train.py`` rejects a bad config, file or device in
about 2 s instead of after the ~5 s those imports take; torch is imported only when a checkpoint is read or a
CUDA device asked.
"""

from __future__ import annotations

import os

from envs.config import ConfigError
from shield_nav.training.config import (
    CHECKPOINT_FORMAT_VERSION,
    TrainConfig,
    migrate_class_paths,
    migrate_flat_algorithm,
)

__all__ = ["check_checkpoint", "check_device", "check_files", "in_run_folder", "read_checkpoint_infos"]


def in_run_folder(checkpoint: str | os.PathLike) -> bool:
    """Whether ``checkpoint`` sits in a training run's folder (tensorboard events beside it).

    ``--resume`` continues such a run in its folder; a packaged policy (``checkpoints/<name>/model.pt``) has none and
    continues in a new run folder.
    """
    folder = os.path.dirname(os.path.abspath(checkpoint))
    return os.path.isdir(folder) and any(f.startswith("events.out.tf") for f in os.listdir(folder))


def check_device(device: str) -> None:
    """Fail before any folder is made if ``device`` names CUDA that this torch build or machine does not have."""
    if not device.startswith("cuda"):
        return
    import torch

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
    import torch  # here, not at module level: the CLI's checks of a config run without torch

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


def read_checkpoint_infos(path: str | os.PathLike, what: str = "checkpoint") -> dict:
    """The ``infos`` of a checkpoint, migrated to the current format (``ValueError`` if unknown or unreadable).

    A missing or unreadable file fails as in :func:`check_checkpoint`, naming ``what`` (the flag or key of the path).
    """
    ckpt = check_checkpoint(path, what)
    infos = ckpt.get("infos") or {}
    version = infos.get("format_version")
    if version is None:
        raise ValueError(f"{path}: no format_version in infos; not written by shield_nav.training")
    if version > CHECKPOINT_FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {version} is newer than this code ({CHECKPOINT_FORMAT_VERSION})")
    if version == 1 and isinstance(infos.get("config"), dict):
        # Version 2 types runner.algorithm by its class (training.config.ALGORITHM_CONFIGS); version 1 stored the
        # flat section with every algorithm's keys.
        infos = {**infos, "config": migrate_flat_algorithm(infos["config"], str(path)), "format_version": 2}
    if isinstance(infos.get("config"), dict):  # checkpoints written before the layout by role name old modules
        infos = {**infos, "config": migrate_class_paths(infos["config"])}
    return infos
