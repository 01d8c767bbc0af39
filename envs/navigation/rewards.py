"""The paper's reward terms, one small function each ("Reward Function Design", "Model-based Reward Shaping").

Every term is signed (penalties are <= 0) and unscaled; the env multiplies each by ``reward.scales[name]`` in one
place and logs it as ``reward/<name>``. All inputs are (N, ...) numpy arrays; outputs are (N,) float64.
"""

from __future__ import annotations

import numpy as np


def navigation(phi_prev: np.ndarray, phi_now: np.ndarray, lam: float, clamp: float) -> np.ndarray:
    """Progress along the potential: lambda * clamp(Phi(p_{t-1}) - Phi(p_t), -C, C)."""
    return lam * np.clip(phi_prev - phi_now, -clamp, clamp)


def safety(
    esdf: np.ndarray, grad: np.ndarray, vel_w: np.ndarray, gamma: float, d_safe: float, delta_min: float
) -> np.ndarray:
    """CBF shaping: clip(bdot + gamma * b, delta_min, 0), b = d(x) - d_safe, bdot = grad d(x) . v."""
    b = esdf - d_safe
    b_dot = np.sum(grad * vel_w, axis=1)
    return np.clip(b_dot + gamma * b, delta_min, 0.0)


def smooth(action: np.ndarray, prev_action: np.ndarray, w_magnitude: float) -> np.ndarray:
    """Control regularisation: -(w |a|^2 + |a - a_prev|^2) on normalised actions."""
    return -(w_magnitude * np.sum(action * action, axis=1) + np.sum((action - prev_action) ** 2, axis=1))


def collision(collided: np.ndarray) -> np.ndarray:
    """Terminal collision penalty: -1 on the step the episode ends in a collision."""
    return -collided.astype(np.float64)


def success(succeeded: np.ndarray) -> np.ndarray:
    """Terminal success bonus: +1 on the step the vehicle reaches the goal."""
    return succeeded.astype(np.float64)


def speed(vel_w: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Soft speed limit: -max(0, |v| - v_target)^2 [(m/s)^2]."""
    over = np.maximum(0.0, np.linalg.norm(vel_w, axis=1) - target)
    return -over * over


def height(z: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Soft altitude band: -(max(0, lo - z) + max(0, z - hi)) [m]."""
    return -(np.maximum(0.0, lo - z) + np.maximum(0.0, z - hi))
