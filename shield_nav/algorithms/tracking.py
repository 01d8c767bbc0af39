"""Velocity tracking shared by the weight-free controllers and the expert.

:func:`accel_to_command` turns a desired world-frame acceleration into a flyable command with the shield's
acceleration model ``a = f_n R(phi, theta, psi) e3 - g e3`` (drag neglected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from envs.config import require
from shield_nav.safety.shield import command_from_accel


@dataclass
class TrackingConfig:
    """Velocity tracking shared by the baselines: a = k_v (v_des - v), clipped to a flyable thrust vector."""

    k_v: float = 2.5
    """Velocity gain [1/s]."""
    max_tilt_deg: float = 40.0
    """Tilt cap of the commanded thrust vector [deg] (the vehicle clamps at 50 deg)."""
    thrust_range: list[float] = field(default_factory=lambda: [2.0, 25.0])
    """Mass-normalised thrust range [m/s^2] (the policies' action range)."""

    def validate(self, prefix: str = "") -> None:
        """Positive gain, sane limits."""
        require(self.k_v > 0, f"{prefix}k_v", "must be > 0")
        require(0 < self.max_tilt_deg < 60, f"{prefix}max_tilt_deg", "must be in (0, 60)")
        require(0 < self.thrust_range[0] < self.thrust_range[1], f"{prefix}thrust_range", "must be 0 < lo < hi")


def accel_to_command(accel_w: np.ndarray, psi: np.ndarray, cfg: TrackingConfig, gravity: float = 9.81) -> np.ndarray:
    """Flyable command (N, 4) for desired accelerations (N, 3) and yaws (N,).

    Thrust vector T = a + g e3. Vertical priority: T_z is clipped to [thrust_lo, thrust_hi], the horizontal part
    to |T_xy| <= T_z tan(max_tilt), then T is scaled down to |T| <= thrust_hi. The command follows from T with
    the shield's inverse model (:func:`shield_nav.safety.shield.command_from_accel`).
    """
    lo, hi = cfg.thrust_range
    t = np.asarray(accel_w, dtype=np.float64) + np.array([0.0, 0.0, gravity])
    t[:, 2] = np.clip(t[:, 2], lo, hi)
    h = np.linalg.norm(t[:, :2], axis=1)
    cap = t[:, 2] * math.tan(math.radians(cfg.max_tilt_deg))
    scale = np.where(h > cap, cap / np.maximum(h, 1e-12), 1.0)
    t[:, :2] *= scale[:, None]
    norm = np.linalg.norm(t, axis=1)
    t *= np.minimum(1.0, hi / np.maximum(norm, 1e-12))[:, None]
    return command_from_accel(t - np.array([0.0, 0.0, gravity]), np.asarray(psi, dtype=np.float64), gravity)
