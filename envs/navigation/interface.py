"""The policy's interface to the vehicle as pure functions: its state vector and its action <-> command mapping.

:class:`~envs.navigation.env.NavigationEnv` builds its observations and flies its actions through these, and a
deployed policy (``shield_nav.deploy``) calls the same functions on the quantities its own state estimate gives, so
a policy reads the same numbers and its actions mean the same commands in simulation and on a vehicle. Shapes:
``N`` vehicles; frames are suffixed (``_w`` world, ``_b`` body); ``R_wb`` rotates body vectors into the world frame.
"""

from __future__ import annotations

import math

import numpy as np

from envs.navigation.config import ActionConfig

__all__ = ["action_to_command", "command_to_action", "headings", "policy_state", "yaw_bases"]


def headings(R_wb: np.ndarray) -> np.ndarray:  # noqa: N803
    """Heading (N,) [rad] of ``R_wb`` (N, 3, 3): the yaw of the body x axis, the camera's axis on the ground."""
    return np.arctan2(R_wb[:, 1, 0], R_wb[:, 0, 0])


def yaw_bases(cfg: ActionConfig, R_wb: np.ndarray, vel_w: np.ndarray) -> np.ndarray:  # noqa: N803
    """The heading (N,) [rad] the yaw action leads from (``cfg.yaw_base``).

    ``heading``: :func:`headings`. ``velocity``: the horizontal velocity's heading, blended towards the current
    heading below ``cfg.yaw_base_speed`` (weight ``min(|v_h| / yaw_base_speed, 1)`` on the wrapped difference), so the
    base is continuous through hover and equal to the heading at rest.
    """
    heading = headings(R_wb)
    if cfg.yaw_base == "heading":
        return heading
    speed = np.hypot(vel_w[:, 0], vel_w[:, 1])
    diff = (np.arctan2(vel_w[:, 1], vel_w[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi
    return heading + np.minimum(speed / cfg.yaw_base_speed, 1.0) * diff


def action_to_command(action: np.ndarray, yaw_base: np.ndarray, cfg: ActionConfig, gravity: float) -> np.ndarray:
    """Normalised actions (N, 4) in [-1, 1] -> vehicle commands (N, 4) = [f_n m/s^2, phi, theta, psi rad].

    ``f_n``: piecewise linear, -1 -> ``thrust_min``, 0 -> ``gravity`` (hover), +1 -> ``thrust_max``; roll and pitch:
    ``a * max_tilt_deg``; yaw: ``yaw_base + a * yaw_range_deg`` (a heading lead).
    """
    a0 = action[:, 0]
    f_n = np.where(a0 >= 0, gravity + a0 * (cfg.thrust_max - gravity), gravity + a0 * (gravity - cfg.thrust_min))
    tilt = math.radians(cfg.max_tilt_deg)
    psi = yaw_base + action[:, 3] * math.radians(cfg.yaw_range_deg)
    return np.stack((f_n, action[:, 1] * tilt, action[:, 2] * tilt, psi), axis=1)


def command_to_action(command: np.ndarray, yaw_base: np.ndarray, cfg: ActionConfig, gravity: float) -> np.ndarray:
    """Inverse of :func:`action_to_command` at the same yaw bases, unclipped: (N, 4) -> (N, 4)."""
    f_n = command[:, 0]
    a0 = np.where(f_n >= gravity, (f_n - gravity) / (cfg.thrust_max - gravity),
                  (f_n - gravity) / (gravity - cfg.thrust_min))  # fmt: skip
    tilt = math.radians(cfg.max_tilt_deg)
    d_psi = (command[:, 3] - yaw_base + np.pi) % (2 * np.pi) - np.pi
    return np.stack((a0, command[:, 1] / tilt, command[:, 2] / tilt, d_psi / math.radians(cfg.yaw_range_deg)), 1)


def policy_state(
    pos: np.ndarray,
    R_wb: np.ndarray,  # noqa: N803
    vel_b: np.ndarray,
    prev_action: np.ndarray,
    goal: np.ndarray,
    target_speed: np.ndarray,
) -> np.ndarray:
    """The policy's (N, 21) state vector (``envs.navigation.STATE_LAYOUT``), float64.

    Args:
        pos: Position (N, 3) [m], in the frame of ``goal`` (z is the height above the ground).
        R_wb: Attitude (N, 3, 3), body -> that frame.
        vel_b: Body-frame velocity (N, 3) [m/s].
        prev_action: The normalised action executed at the previous control step (N, 4).
        goal: Goal point (N, 3) [m].
        target_speed: Target speed (N,) [m/s].
    """
    psi = np.arctan2(R_wb[:, 1, 0], R_wb[:, 0, 0])
    d = goal[:, :2] - pos[:, :2]
    c, s = np.cos(psi), np.sin(psi)
    d_h = np.stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]), axis=1)  # Rz(-psi) d
    d_h /= np.maximum(np.linalg.norm(d_h, axis=1, keepdims=True), 10.0)
    return np.concatenate(
        (
            vel_b / 10.0,  # 3
            R_wb.reshape(len(R_wb), 9),  # 9
            prev_action,  # 4
            d_h,  # 2
            pos[:, 2:3] / 3.0,  # 1
            goal[:, 2:3] / 3.0,  # 1
            target_speed[:, None] / 10.0,  # 1
        ),
        axis=1,
    )
