"""Batched rotation helpers on numpy arrays. Quaternions are (w, x, y, z), Hamilton product, body-to-world.

All functions take arrays with a leading batch dimension (N, ...) and never loop over it in Python. The two on the
physics hot path (:func:`quat_mul`, :func:`quat_to_rot`, called several times per physics substep) run float64
inputs through small numba kernels: the same products and sums in the same order as the numpy expressions (no
fused multiply-add), so the result is theirs to the bit, without numpy's per-call overhead on small batches.
Euler angles are ZYX (yaw psi about z, then pitch theta about y, then roll phi about x): R = Rz(psi) Ry(theta) Rx(phi).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=False, inline="always")
def quat_mul_scalars(
    w1: float, x1: float, y1: float, z1: float, w2: float, x2: float, y2: float, z2: float
) -> tuple[float, float, float, float]:
    """Hamilton product (w1, x1, y1, z1) * (w2, x2, y2, z2) of scalars, for numba kernels (inlined into them).

    The products and sums of :func:`quat_mul`'s numpy expressions, in their order: the kernels that call it equal
    the numpy formulation to the bit.
    """
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


@numba.njit(cache=True, fastmath=False)
def _quat_mul_kernel(q: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    for i in range(q.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = quat_mul_scalars(
            q[i, 0], q[i, 1], q[i, 2], q[i, 3], p[i, 0], p[i, 1], p[i, 2], p[i, 3]
        )


@numba.njit(cache=True, fastmath=False)
def _quat_to_rot_kernel(q: np.ndarray, r: np.ndarray) -> None:
    for i in range(q.shape[0]):
        w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        r[i, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
        r[i, 0, 1] = 2.0 * (x * y - w * z)
        r[i, 0, 2] = 2.0 * (x * z + w * y)
        r[i, 1, 0] = 2.0 * (x * y + w * z)
        r[i, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
        r[i, 1, 2] = 2.0 * (y * z - w * x)
        r[i, 2, 0] = 2.0 * (x * z - w * y)
        r[i, 2, 1] = 2.0 * (y * z + w * x)
        r[i, 2, 2] = 1.0 - 2.0 * (x * x + y * y)


def _float64_rows(a: np.ndarray) -> np.ndarray | None:
    """``a`` as contiguous (M, 4) float64 rows for a kernel, or None where the numpy expressions must run.

    Another dtype keeps numpy's arithmetic (the kernels would change it).
    """
    if not isinstance(a, np.ndarray) or a.dtype != np.float64 or a.ndim < 1 or a.shape[-1] != 4:
        return None
    return np.ascontiguousarray(a.reshape(-1, 4))


def quat_mul(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Hamilton product q * p. Shapes (N, 4) x (N, 4) -> (N, 4)."""
    if isinstance(q, np.ndarray) and isinstance(p, np.ndarray) and q.shape == p.shape:
        qr, pr = _float64_rows(q), _float64_rows(p)
        if qr is not None and pr is not None:
            out = np.empty(qr.shape)
            _quat_mul_kernel(qr, pr, out)
            return out.reshape(q.shape)
    w1, x1, y1, z1 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    w2, x2, y2, z2 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    return np.stack(
        (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ),
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion). (N, 4) -> (N, 4)."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices R_wb from unit quaternions. (N, 4) -> (N, 3, 3)."""
    rows = _float64_rows(q)
    if rows is not None:
        r = np.empty((rows.shape[0], 3, 3))
        _quat_to_rot_kernel(rows, r)
        return r.reshape((*q.shape[:-1], 3, 3))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty((*q.shape[:-1], 3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (w >= 0) from rotation matrices, numerically stable branch per element. (N,3,3) -> (N,4)."""
    tr = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    # Four candidate formulas; pick the one with the largest (well-conditioned) square root per element.
    cand = np.stack((tr, r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]), axis=-1)
    k = np.argmax(cand, axis=-1)
    r00, r01, r02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    r10, r11, r12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    r20, r21, r22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    s0 = np.sqrt(np.maximum(1.0 + tr, 1e-12)) * 2.0  # 4w
    s1 = np.sqrt(np.maximum(1.0 + r00 - r11 - r22, 1e-12)) * 2.0  # 4x
    s2 = np.sqrt(np.maximum(1.0 + r11 - r00 - r22, 1e-12)) * 2.0  # 4y
    s3 = np.sqrt(np.maximum(1.0 + r22 - r00 - r11, 1e-12)) * 2.0  # 4z
    q0 = np.stack((0.25 * s0, (r21 - r12) / s0, (r02 - r20) / s0, (r10 - r01) / s0), axis=-1)
    q1 = np.stack(((r21 - r12) / s1, 0.25 * s1, (r01 + r10) / s1, (r02 + r20) / s1), axis=-1)
    q2 = np.stack(((r02 - r20) / s2, (r01 + r10) / s2, 0.25 * s2, (r12 + r21) / s2), axis=-1)
    q3 = np.stack(((r10 - r01) / s3, (r02 + r20) / s3, (r12 + r21) / s3, 0.25 * s3), axis=-1)
    q = np.where((k == 0)[..., None], q0, np.where((k == 1)[..., None], q1, np.where((k == 2)[..., None], q2, q3)))
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def euler_zyx_to_rot(phi: np.ndarray, theta: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """R = Rz(psi) Ry(theta) Rx(phi) from roll, pitch, yaw (rad). Each (N,) -> (N, 3, 3)."""
    cf, sf = np.cos(phi), np.sin(phi)
    ct, st = np.cos(theta), np.sin(theta)
    cp, sp = np.cos(psi), np.sin(psi)
    r = np.empty((*np.shape(phi), 3, 3))
    r[..., 0, 0] = cp * ct
    r[..., 0, 1] = cp * st * sf - sp * cf
    r[..., 0, 2] = cp * st * cf + sp * sf
    r[..., 1, 0] = sp * ct
    r[..., 1, 1] = sp * st * sf + cp * cf
    r[..., 1, 2] = sp * st * cf - cp * sf
    r[..., 2, 0] = -st
    r[..., 2, 1] = ct * sf
    r[..., 2, 2] = ct * cf
    return r


def rot_to_euler_zyx(r: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_zyx_to_rot`: (N, 3, 3) -> (N, 3) as (phi, theta, psi) in rad."""
    phi = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    theta = -np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0))
    psi = np.arctan2(r[..., 1, 0], r[..., 0, 0])
    return np.stack((phi, theta, psi), axis=-1)


def attitude_from_thrust_axis(z_d: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Rotation whose body z axis is the unit vector ``z_d`` (N,3) and whose heading is ``psi`` (N,).

    This is PX4's ``bodyzToAttitude``: x_b = normalize(y_c x z_d) with y_c = (-sin psi, cos psi, 0), y_b = z_d x x_b.
    For |roll| < 90 deg it reproduces ``euler_zyx_to_rot(phi, theta, psi)`` exactly when z_d = R e3.
    """
    y_c = np.stack((-np.sin(psi), np.cos(psi), np.zeros_like(psi)), axis=-1)
    x_b = np.cross(y_c, z_d)
    n = np.linalg.norm(x_b, axis=-1, keepdims=True)
    # z_d horizontal and along y_c is degenerate (roll of 90 deg); fall back to the heading's x axis.
    fallback = np.stack((np.cos(psi), np.sin(psi), np.zeros_like(psi)), axis=-1)
    x_b = np.where(n > 1e-9, x_b / np.maximum(n, 1e-12), fallback)
    y_b = np.cross(z_d, x_b)
    return np.stack((x_b, y_b, z_d), axis=-1)


def wrap_pi(a: np.ndarray) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi
