"""The training config as rsl-rl's runners take it.

A plain dict, each class's section holding only the keys its constructor takes.
"""

from __future__ import annotations

import copy
import inspect

from envs.config import to_dict
from shield_nav.training.config import MULTI_HYPOTHESIS_ALGORITHM, SCHEDULED_ALGORITHM, TrainConfig


def _constructor_names(class_name: str) -> set[str] | None:
    """Parameter names ``class_name``'s constructor chain takes (None: it takes any keyword).

    A subclass that forwards ``**kwargs`` to its parent (shield_nav.algorithms.anchored.AnchoredPPO -> PPO) takes what
    the first class up its MRO without ``**kwargs`` takes; if every ``__init__`` takes ``**kwargs``, anything is passed
    on.
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
    for key in (
        "init_at_random_ep_len",
        "class_name",
        "teacher_checkpoint",
        "student_init",
        "expert",
        "actor_init",
        "critic_warmup_iterations",
        "average_iterations",
    ):
        d.pop(key)
    teacher = d.pop("teacher")
    if cfg.runner.class_name == "DistillationRunner":
        d["student"] = d.pop("actor")
        d["teacher"] = teacher
        d.pop("critic")
    if d["algorithm"].get("lr_schedule_iterations") == 0:
        d["algorithm"]["lr_schedule_iterations"] = cfg.max_iterations
    if d["algorithm"]["class_name"] in (SCHEDULED_ALGORITHM, MULTI_HYPOTHESIS_ALGORITHM):
        d["algorithm"]["seed"] = cfg.seed  # the draw of replayed rollouts
    for key in ("actor", "critic", "student", "teacher"):  # the algorithm section is typed by its class already
        if key in d:
            d[key] = _accepted(d[key]["class_name"], d[key])
    d["experiment_name"] = cfg.experiment_name
    d["run_name"] = cfg.name
    d["seed"] = cfg.seed
    return copy.deepcopy(d)


# ------------------------------------------------------------------------------------------------ runner
