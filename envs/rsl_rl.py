"""rsl-rl adapter: :class:`envs.navigation.NavigationEnv` as an ``rsl_rl.env.VecEnv`` with TensorDict observations.

Observation groups (map them with the runner's ``obs_groups``, e.g. ``{"actor": ["depth", "state"],
"critic": ["critic"]}``):

========  ====================  ==========================================================
group     shape                 content
========  ====================  ==========================================================
depth     (N, 1, 60, 100)       noisy normalised depth (policy)
state     (N, 21)               noisy proprioception and goal (policy), see ``STATE_LAYOUT``
memory    (N, B)                onboard scene memory, nearest remembered obstacle per bearing sector (policy;
                                only with ``env.scene_memory.enabled``)
clock     (N, 1)                the slack to the time limit (policy; only with ``env.episode.clock_input``)
critic    (N, C)                noise-free privileged vector (critic only)
teacher   (N, 21 + M)           clean state + privileged local ESDF map (only with ``env.local_map.enabled``;
                                a privileged teacher's input, see docs/training.md "Teacher-student")
expert    (N, 4)                a scripted expert's normalised action for the current state (only when the
                                adapter is built with ``expert=``; the label of oracle-DAgger distillation)
========  ====================  ==========================================================

With a ``command_filter`` (the HOCBF shield in the loop, ``shield_in_loop`` of the train config), every step's
actions are mapped to commands, filtered, and the filtered commands are flown (``NavigationEnv.step(commands=)``):
the learner trains the system it is deployed as; ``extras["log"]["shield/active"]`` is the share of envs whose command
the filter changed that step and ``shield/correction`` the mean size of the change [m/s^2]. With ``filter_penalty``
(``shield_penalty`` of the train config) each step's reward loses that times the env's change, logged as
``reward/shield``. With ``view_penalty`` (the train config's key of that name) it loses that times
:func:`outside_view`, how far the vehicle flies outside its camera's view, logged as ``reward/view``.

``extras["time_outs"]`` (N,) marks truncations for bootstrapping; ``extras["log"]`` holds per-step reward-term means
and, for finished episodes, their outcomes (success, collision, timeout, out of bounds), mean speed and clearance,
which rsl-rl's logger averages per iteration and writes to tensorboard.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from envs.navigation import NavigationEnv


class CommandFilter(Protocol):
    """A per-step command filter between the learner's actions and the vehicles (e.g. the HOCBF shield)."""

    def __call__(self, env: NavigationEnv, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The commands (N, 4) to fly, which the filter changed (N,), and by how much (N,) [m/s^2].

        ``actions`` (N, 4) are normalised; the size of a change is that of the commanded acceleration.
        """
        ...

    def reset(self, ids: np.ndarray) -> None:
        """Forget per-vehicle memory of envs ``ids`` (they start a new episode)."""
        ...


def outside_view(env: NavigationEnv) -> np.ndarray:
    """How far [rad] each vehicle's horizontal velocity points outside its camera's horizontal view, (N,).

    The angle between the horizontal velocity and the heading (the camera axis projected on the ground) beyond half
    the horizontal field of view, times a ramp from 0 at 0.5 m/s to 1 at 1.5 m/s of horizontal speed (a hovering
    vehicle's velocity direction is noise).
    """
    r = env.vehicles.R_wb
    hx, hy = r[:, 0, 0], r[:, 1, 0]
    v = env.vehicles.vel_w
    ang = np.abs(np.arctan2(hx * v[:, 1] - hy * v[:, 0], hx * v[:, 0] + hy * v[:, 1]))
    speed = np.hypot(v[:, 0], v[:, 1])
    half = np.radians(env.cfg.camera.hfov_deg) / 2.0
    return np.maximum(0.0, ang - half) * np.clip(speed - 0.5, 0.0, 1.0)


class RslRlVecEnv(VecEnv):
    """Wraps a :class:`NavigationEnv` (numpy) for rsl-rl (torch). Shapes are stated in the module docstring.

    Args:
        env: The batched navigation env.
        device: Torch device for the returned tensors.
        expert: Optional expert ``expert(env) -> (N, 4)`` normalised actions, evaluated once on every new
            observation (after resets too) and returned as the ``expert`` group. It may remember the last call (the
            planner's route hysteresis) but must not assume a step between two calls.
        expert_flown_share: DAgger's mixing share (Ross et al. 2011's beta): at every episode start each env is
            drawn, with this probability, to fly the episode on the expert's labels instead of the actions it is
            given (the student's); the ``expert`` group labels every state either way. 0 (default): the student
            flies always.
    """

    def __init__(
        self,
        env: NavigationEnv,
        device: str | torch.device = "cpu",
        expert: Callable[[NavigationEnv], np.ndarray] | None = None,
        command_filter: CommandFilter | None = None,
        filter_penalty: float = 0.0,
        view_penalty: float = 0.0,
        expert_flown_share: float = 0.0,
    ) -> None:  # noqa: D107
        if not (np.isfinite(expert_flown_share) and 0.0 <= expert_flown_share <= 1.0):
            raise ValueError(f"expert_flown_share must be in [0, 1], got {expert_flown_share}")
        if expert_flown_share and expert is None:
            raise ValueError(f"expert_flown_share {expert_flown_share} needs an expert")
        if not (np.isfinite(filter_penalty) and filter_penalty >= 0):
            raise ValueError(f"filter_penalty must be a finite number >= 0, got {filter_penalty}")
        if filter_penalty and command_filter is None:
            raise ValueError(f"filter_penalty {filter_penalty} needs a command_filter")
        self.env = env
        self.expert = expert
        self.command_filter = command_filter
        self.filter_penalty = float(filter_penalty)
        if not (np.isfinite(view_penalty) and view_penalty >= 0):
            raise ValueError(f"view_penalty must be a finite number >= 0, got {view_penalty}")
        self.view_penalty = float(view_penalty)
        self.cfg = env.cfg
        self.device = torch.device(device)
        self.num_envs = env.num_envs
        self.num_actions = 4
        self.expert_flown_share = float(expert_flown_share)
        self._share_rng = np.random.default_rng([env.cfg.seed, 0xBE7A])  # its own stream: the env's draws unchanged
        self.expert_flown = np.zeros(env.num_envs, dtype=bool)  # envs whose episode flies the expert's labels
        self._draw_expert_flown(np.arange(env.num_envs))
        obs, info = env.reset(seed=env.cfg.seed)
        self._obs = self._to_tensordict(obs, info)

    @property
    def max_episode_length(self) -> int:
        """The longest per-env time limit in steps.

        Each env's own limit is ``env.max_episode_length_buf``; rsl-rl calls ``int()`` on this for its random initial
        episode lengths, which the ``episode_length_buf`` setter clamps per env.
        """
        return int(self.env.max_episode_length_buf.max())

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Current episode lengths (N,); assigning to it (rsl-rl's random initial lengths) writes through."""
        return torch.from_numpy(self.env.episode_length_buf.copy()).to(self.device)

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.env.episode_length_buf[:] = np.minimum(
            value.detach().cpu().numpy().astype(np.int64), self.env.max_episode_length_buf - 1
        )

    def _draw_expert_flown(self, ids: np.ndarray) -> None:
        if self.expert_flown_share:
            self.expert_flown[ids] = self._share_rng.random(len(ids)) < self.expert_flown_share

    def _to_tensordict(self, obs: dict, info: dict) -> TensorDict:
        data = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in obs.items()}
        for k in ("critic", "teacher"):
            if k in info:
                data[k] = torch.from_numpy(np.ascontiguousarray(info[k]))
        if self.expert is not None:
            data["expert"] = torch.from_numpy(np.asarray(self.expert(self.env), dtype=np.float32))
        return TensorDict(data, batch_size=[self.num_envs], device=self.device)

    @property
    def curriculum_active(self) -> bool:
        """Whether resets draw each env's scene from its curriculum level (:attr:`NavigationEnv.curriculum_active`)."""
        return self.env.curriculum_active

    @property
    def num_scenes(self) -> int:
        """Length of the training scene list (the range of the curriculum levels)."""
        return len(self.env.scenes)

    @property
    def curriculum_levels(self) -> list[int]:
        """Each env's curriculum level (scene index into the training list)."""
        return self.env.level_buf.tolist()

    def set_curriculum_levels(self, levels: list[int]) -> None:
        """Install saved levels (a resumed run) and restart every episode on its level."""
        lv = np.asarray(levels, dtype=np.int64)
        if lv.shape != (self.num_envs,) or lv.min() < 0 or lv.max() >= len(self.env.scenes):
            raise ValueError(f"curriculum levels must be {self.num_envs} ints in 0..{len(self.env.scenes) - 1}")
        self.env.level_buf[:] = lv
        if self.command_filter is not None:
            self.command_filter.reset(np.arange(self.num_envs))
        self._draw_expert_flown(np.arange(self.num_envs))
        obs, info = self.env.reset()
        self._obs = self._to_tensordict(obs, info)

    def get_observations(self) -> TensorDict:
        """The current observation groups."""
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Step with actions (N, 4); returns observations, rewards (N,), dones (N,) and extras."""
        act = actions.detach().cpu().numpy().astype(np.float64)
        if self.expert_flown.any():  # DAgger's mixing: these envs fly the label of the current observation
            act[self.expert_flown] = self._obs["expert"].cpu().numpy()[self.expert_flown]
        commands = active = correction = None
        if self.command_filter is not None:
            commands, active, correction = self.command_filter(self.env, act)
        obs, rew, term, trunc, info = self.env.step(act, commands=commands)
        penalty = None
        if self.filter_penalty:
            penalty = -self.filter_penalty * correction
            rew = rew + penalty
        view = None
        if self.view_penalty:
            view = -self.view_penalty * np.where(term | trunc, 0.0, outside_view(self.env))
            rew = rew + view
        if self.command_filter is not None:
            self.command_filter.reset(np.flatnonzero(term | trunc))
        self._obs = self._to_tensordict(obs, info)
        log = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in info["log"].items()}
        if self.expert_flown_share:
            log["dagger/expert_flown"] = torch.as_tensor(float(np.mean(self.expert_flown)), dtype=torch.float32)
            self._draw_expert_flown(np.flatnonzero(term | trunc))
        if active is not None:
            log["shield/active"] = torch.as_tensor(float(np.mean(active)), dtype=torch.float32)
            log["shield/correction"] = torch.as_tensor(float(np.mean(correction)), dtype=torch.float32)
        if penalty is not None:
            log["reward/shield"] = torch.as_tensor(float(np.mean(penalty)), dtype=torch.float32)
        if view is not None:
            log["reward/view"] = torch.as_tensor(float(np.mean(view)), dtype=torch.float32)
        extras = {"time_outs": torch.from_numpy(trunc).to(self.device), "log": log}
        dones = torch.from_numpy(term | trunc).to(self.device)
        return self._obs, torch.from_numpy(rew.astype(np.float32)).to(self.device), dones, extras
