"""The deployable actor of a training checkpoint, rebuilt from the config the checkpoint stored (no env needed).

Read by the evaluation (``network: fixed_order`` on a ``model_<it>.pt``), the release packaging
(:mod:`shield_nav.tools.package`), ensembles and the imitation measure.
"""

from __future__ import annotations

import torch
from rsl_rl.utils import resolve_callable
from tensordict import TensorDict

from envs.config import stored_config
from envs.navigation import STATE_DIM
from shield_nav.policies.models import DepthGRUModel
from shield_nav.training.checks import read_checkpoint_infos
from shield_nav.training.config import TrainConfig, load_train_config
from shield_nav.training.rsl_rl_cfg import rsl_rl_train_cfg


def actor_from_checkpoint(ckpt_path: str) -> tuple[DepthGRUModel | None, TrainConfig, dict]:
    """Rebuild the deployable actor of a checkpoint from its stored config (no env needed).

    PPO checkpoints give their actor, distillation checkpoints their student; a privileged teacher (its actor is not
    a ``DepthGRUModel``) gives ``None``.
    """
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    infos = read_checkpoint_infos(ckpt_path)
    stored = infos.get("config")
    cfg = load_train_config(overrides=stored_config(TrainConfig, stored)) if isinstance(stored, dict) else None
    if cfg is None:
        raise ValueError(f"{ckpt_path}: the checkpoint carries no resolved config")
    meta = {"iter": int(ckpt["iter"]), **{k: v for k, v in infos.items() if k != "config"}}
    if isinstance(meta.get("weight_average"), dict):  # a running average's tensors do not belong in meta.json
        meta["weight_average"] = {k: v for k, v in meta["weight_average"].items() if k != "mean"}
    distilled = cfg.runner.class_name == "DistillationRunner"
    obs_set, key = ("student", "student_state_dict") if distilled else ("actor", "actor_state_dict")
    train_cfg = rsl_rl_train_cfg(cfg)
    if resolve_callable(train_cfg[obs_set]["class_name"]) is not DepthGRUModel:
        return None, cfg, meta
    cam = cfg.env.camera
    obs = TensorDict(
        {"depth": torch.zeros(1, 1, cam.height, cam.width), "state": torch.zeros(1, STATE_DIM)}, batch_size=[1]
    )
    groups = {obs_set: cfg.runner.obs_groups[obs_set]}
    actor_kwargs = {k: v for k, v in train_cfg[obs_set].items() if k != "class_name"}
    model = DepthGRUModel(obs, groups, obs_set, 4, **actor_kwargs)
    model.load_state_dict(ckpt[key])
    model.eval()
    return model, cfg, meta
