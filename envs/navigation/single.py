"""``ShieldNavEnv``: the single-vehicle ``gymnasium.Env`` view of :class:`NavigationEnv` (``gymnasium.make``)."""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np

from envs.navigation.config import NavConfig
from envs.navigation.env import NavigationEnv


class ShieldNavEnv(gym.Env):
    """One vehicle of the navigation task with the standard gymnasium single-env API.

    It wraps a :class:`NavigationEnv` with ``num_envs = 1`` and no autoreset: after ``terminated`` or
    ``truncated`` call :meth:`reset`. Spaces, action mapping, observation layout and rewards are those of
    :class:`NavigationEnv`; ``info["critic"]`` holds the privileged vector (C,).

    Args:
        config: A :class:`NavConfig`, a YAML path, or None.
        render_mode: Not supported (None); use ``eval.py --video`` for videos.
        **kwargs: Dotted config overrides.
    """

    metadata = {"render_modes": []}

    def __init__(self, config: NavConfig | str | os.PathLike | None = None, render_mode: str | None = None,
                 **kwargs: Any) -> None:  # fmt: skip
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported")
        kwargs["autoreset"] = False
        self.vec = NavigationEnv(num_envs=1, config=config, **kwargs)
        self.observation_space = self.vec.single_observation_space
        self.action_space = self.vec.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:  # noqa: D102
        super().reset(seed=seed)
        obs, info = self.vec.reset(seed=seed, options=options)
        return {k: v[0] for k, v in obs.items()}, {"critic": info["critic"][0]}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:  # noqa: D102
        obs, rew, term, trunc, info = self.vec.step(np.asarray(action, dtype=np.float64)[None])
        out = {"critic": info["critic"][0], "log": info["log"]}
        for k in ("success", "collision", "out_of_bounds", "time_outs"):
            out[k] = bool(info[k][0])
        return {k: v[0] for k, v in obs.items()}, float(rew[0]), bool(term[0]), bool(trunc[0]), out
