"""The HOCBF shield in the training loop: the learner's rollouts fly the deployed system (policy behind the shield).

``train.py`` builds it when the train config sets ``shield_in_loop: true`` (with the shield's own keys under
``shield:``, :class:`shield_nav.safety.shield.ShieldConfig`) and hands it to :class:`envs.rsl_rl.RslRlVecEnv` as its
``command_filter``. Each step the actions are mapped to commands, filtered exactly as the evaluation harness filters
the Full row (``shield_nav/evaluation/rollout.py``: the sensor's depth image, the body attitude it was taken at, the
env-local position and the velocity), and the filtered commands are flown. PPO keeps the sampled action as its action
(the shield is part of the environment it learns in); a DAgger student's visited states are those of the student
behind the shield, which the expert then labels. docs/training.md, "The shield in the loop".
"""

from __future__ import annotations

import numpy as np

from envs.camera import CameraConfig
from envs.navigation import NavigationEnv
from shield_nav.safety.shield import HOCBFShield, ShieldConfig


class ShieldInLoop:
    """A :class:`envs.rsl_rl.CommandFilter` that flies every env's command through one :class:`HOCBFShield`.

    Args:
        cfg: The shield's parameters (the evaluation's defaults unless the train config overrides them).
        camera: The env's camera (the shield back-projects its depth images).
    """

    def __init__(self, cfg: ShieldConfig, camera: CameraConfig) -> None:  # noqa: D107
        self.shield = HOCBFShield(cfg, camera)

    def __call__(self, env: NavigationEnv, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Commands (N, 4) after the shield for normalised ``actions`` (N, 4), which it changed, and by how much.

        The size of a change (N,) is ``|a_safe - a_raw|`` [m/s^2], 0 where the shield changed nothing.
        """
        cmd = env.action_to_command(np.clip(actions, -1.0, 1.0))
        out = self.shield.filter_env(env, cmd)
        correction = np.where(out.active, np.linalg.norm(out.accel_safe - out.accel_raw, axis=1), 0.0)
        return out.command, out.active, correction

    def reset(self, ids: np.ndarray) -> None:
        """Forget the per-vehicle state (previous velocity, point memory) of envs ``ids``."""
        if len(ids):
            self.shield.reset(np.asarray(ids))
