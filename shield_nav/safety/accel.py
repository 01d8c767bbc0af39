"""The shield's acceleration model.

Commands [f_n, phi, theta, psi] to world accelerations and back (PX4's thrust axis and heading), batched and as
scalar numba kernels.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from envs.vehicle.rotations import attitude_from_thrust_axis, euler_zyx_to_rot, rot_to_euler_zyx


# --------------------------------------------------------------------------------------------- acceleration model
def accel_from_command(command: np.ndarray, gravity: float = 9.81) -> np.ndarray:
    """World-frame acceleration of commands (N, 4) = [f_n, phi, theta, psi]: a = f_n R e3 - g e3. Returns (N, 3)."""
    cmd = np.atleast_2d(command)
    z_b = euler_zyx_to_rot(cmd[:, 1], cmd[:, 2], cmd[:, 3])[:, :, 2]
    a = cmd[:, :1] * z_b
    a[:, 2] -= gravity
    return a


def command_from_accel(accel: np.ndarray, psi: np.ndarray, gravity: float = 9.81) -> np.ndarray:
    """Inverse of :func:`accel_from_command` for a given yaw: T = a + g e3, f_n = |T|, body z = T / |T|.

    Roll and pitch follow from the attitude with that thrust axis and heading psi (PX4's bodyzToAttitude).
    Returns (N, 4) = [f_n, phi, theta, psi] with psi unchanged.
    """
    a = np.atleast_2d(accel)
    psi = np.atleast_1d(psi)
    t = a + np.array([0.0, 0.0, gravity])
    f_n = np.linalg.norm(t, axis=1)
    z_d = t / np.maximum(f_n, 1e-12)[:, None]
    euler = rot_to_euler_zyx(attitude_from_thrust_axis(z_d, psi))
    return np.concatenate((f_n[:, None], euler[:, :2], psi[:, None]), axis=1)


@nb.njit(cache=True, nogil=True)
def _accel_from_command_1(f_n: float, phi: float, theta: float, psi: float, g: float, out: np.ndarray) -> None:
    """Scalar :func:`accel_from_command` into ``out`` (3,): a = f_n R(phi, theta, psi) e3 - g e3."""
    cf, sf, ct, st, cp, sp = (
        math.cos(phi),
        math.sin(phi),
        math.cos(theta),
        math.sin(theta),
        math.cos(psi),
        math.sin(psi),
    )
    out[0] = f_n * (cp * st * cf + sp * sf)
    out[1] = f_n * (sp * st * cf - cp * sf)
    out[2] = f_n * ct * cf - g


@nb.njit(cache=True, nogil=True)
def _command_from_accel_1(ax: float, ay: float, az: float, psi: float, g: float) -> tuple[float, float, float]:
    """Scalar :func:`command_from_accel` for one vehicle: returns (f_n, phi, theta)."""
    tx, ty, tz = ax, ay, az + g
    f = math.sqrt(tx * tx + ty * ty + tz * tz)
    zx, zy, zz = tx / f, ty / f, tz / f
    # x_b = normalize(y_c x z) with y_c = (-sin psi, cos psi, 0); y_b = z x x_b.
    yx, yy = -math.sin(psi), math.cos(psi)
    xx, xy, xz = yy * zz, -yx * zz, yx * zy - yy * zx
    n = math.sqrt(xx * xx + xy * xy + xz * xz)
    xx, xy, xz = xx / n, xy / n, xz / n
    ybz = zx * xy - zy * xx
    phi = math.atan2(ybz, zz)  # atan2(R21, R22)
    theta = -math.asin(min(1.0, max(-1.0, xz)))  # -asin(R20)
    return f, phi, theta
