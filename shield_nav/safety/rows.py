"""HOCBF rows: the acceleration model, the barrier rows, and which points of the cloud become rows.

The numba kernels of :mod:`shield_nav.safety.shield` (docs/shield.md, "Derivation", "Which points become constraints"
and "Lag", "Braking barrier"). For a point o and the vehicle at p with velocity v, r = p - o, and the row of the HOCBF
condition is 2 r.a >= -2|v|^2 - alpha1 (2 r.v) - alpha0 (|r|^2 - r_safe^2); the braking barrier's row has the same
A = 2 r and its own right-hand side (``braking_rows``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from shield_nav.safety.sectors import elevation_bounds, sector

PASSING_MIN_SPEED = 0.5
"""[m/s] Below this speed the braking barrier's collision-cone union is off (its row divides by |v|)."""
PASSING_MIN_S = 0.05
"""[m] The cone row needs S = sqrt(|r|^2 - r_safe^2) at least this large (it divides by S); closer, the braking row
alone applies."""

BRAKE_EPS = 1.0e-3
"""[m] Smallest |d - r_safe| the braking barrier divides by (keeps its rows finite at r_safe, where an approach
then asks for far more braking than the vehicle has, and the QP relaxes)."""


def ground_row(z: float, v_z: float, alpha0: float, alpha1: float, min_altitude: float) -> float:
    """Right-hand side b of the ground row a_z >= b: B = z - min_altitude, Bdot = v_z, Bddot = a_z."""
    return -alpha1 * v_z - alpha0 * (z - min_altitude)


def ceiling_row(z: float, v_z: float, alpha0: float, alpha1: float, max_altitude: float) -> float:
    """Right-hand side b of the ceiling row -a_z >= b: B = max_altitude - z, Bdot = -v_z, Bddot = -a_z."""
    return alpha1 * v_z - alpha0 * (max_altitude - z)


def braking_rows(
    r: np.ndarray, v: np.ndarray, r_safe: float, brake_accel: float, gain: float
) -> tuple[np.ndarray, np.ndarray]:
    """Braking-barrier rows A a >= b for offsets r (K, 3) = p - o and velocity v (3,) (docs/shield.md).

    With d = |r|, n = r / d, the closing speed c = -n.v, e = d - r_safe and s = sqrt(2 brake_accel |e|), the barrier
    h = sign(e) s - c (>= 0: braking at ``brake_accel`` along n stops the approach before r_safe; inside r_safe it
    is negative and pushes out) gives the first-order CBF row
    n.a >= -gain h + brake_accel c / s - (|v|^2 - c^2) / d  (s floored at |e| = ``BRAKE_EPS`` in the division),
    written here scaled by 2d as  2 r.a >= 2 d b  so that A = 2 r as for the HOCBF rows.
    """
    r = np.atleast_2d(np.asarray(r, dtype=np.float64))
    v = np.asarray(v, dtype=np.float64)
    d = np.maximum(np.linalg.norm(r, axis=1), 1e-9)
    c = -(r @ v) / d
    e = d - r_safe
    root = np.sqrt(2.0 * brake_accel * np.abs(e))
    s = np.maximum(root, math.sqrt(2.0 * brake_accel * BRAKE_EPS))
    h = np.sign(e) * root - c
    b = -gain * h + brake_accel * c / s - (float(v @ v) - c * c) / d
    return 2.0 * r, 2.0 * d * b


def passing_rows(
    r: np.ndarray, v: np.ndarray, a: np.ndarray, r_safe: float, brake_accel: float, gain: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The braking barrier's rows with its collision-cone union (``passing: true``; docs/shield.md).

    The collision-cone barrier h_c = r.v + |v| S, S = sqrt(|r|^2 - r_safe^2), is >= 0 when v points outside the
    cone the r_safe ball subtends, so that flying straight on passes the point at least r_safe away; its
    first-order row is (r + S v / |v|).a >= -gain h_c - |v|^2 - |v| (r.v) / S, which a = 0 meets whenever h_c >= 0.
    The safe set is the union of {h_b >= 0} (``braking_rows``) and {h_c >= 0}; a point gets the cone row where
    h_c >= 0 and either h_b < 0 or the cone row is nearer to being met at the acceleration ``a`` (row value over
    |A|), else its braking row. The cone is off where |v| <= ``PASSING_MIN_SPEED`` or S < ``PASSING_MIN_S``.
    Returns (A (K, 3), b (K,), cone (K,) bool); A = 2 r for the braking rows.
    """
    r = np.atleast_2d(np.asarray(r, dtype=np.float64))
    v = np.asarray(v, dtype=np.float64)
    a = np.asarray(a, dtype=np.float64)
    a_mat, b = braking_rows(r, v, r_safe, brake_accel, gain)
    d = np.maximum(np.linalg.norm(r, axis=1), 1e-9)
    speed = float(np.linalg.norm(v))
    s2 = d * d - r_safe * r_safe
    ok = (s2 > PASSING_MIN_S**2) & (speed > PASSING_MIN_SPEED)
    s = np.sqrt(np.where(ok, s2, 1.0))
    rv = r @ v
    e = d - r_safe
    h_b = np.sign(e) * np.sqrt(2.0 * brake_accel * np.abs(e)) + rv / d
    h_c = rv + speed * s
    a_cone = r + s[:, None] * (v / max(speed, 1e-12))[None, :]
    b_cone = -gain * h_c - speed * speed - speed * rv / s
    nearer = (a_cone @ a - b_cone) / np.linalg.norm(a_cone, axis=1) > (a_mat @ a - b) / (2.0 * d)
    cone = ok & (h_c >= 0.0) & ((h_b < 0.0) | nearer)
    return np.where(cone[:, None], a_cone, a_mat), np.where(cone, b_cone, b), cone


def backup_distance(r: np.ndarray, v: np.ndarray, brake_accel: float) -> np.ndarray:
    """D: each point's closest distance over the backup maneuver (braking straight along -v to a stop).

    Offsets r (K, 3) = p - o; the maneuver brakes at ``brake_accel`` from p and stops S = |v|^2 / (2 brake_accel)
    further on.

    With u = v / |v|, x = (o - p).u (how far ahead the point lies) and m its distance from the line of v:
    D = |r| for x <= 0, m for 0 < x < S, sqrt((x - S)^2 + m^2) for x >= S.
    """
    r = np.atleast_2d(np.asarray(r, dtype=np.float64))
    v = np.asarray(v, dtype=np.float64)
    speed = float(np.linalg.norm(v))
    u = v / speed
    x = -(r @ u)
    m = np.linalg.norm(r + x[:, None] * u[None, :], axis=1)
    stop = speed * speed / (2.0 * brake_accel)
    d = np.linalg.norm(r, axis=1)
    return np.where(x <= 0.0, d, np.where(x < stop, m, np.hypot(np.maximum(x - stop, 0.0), m)))


def backup_rows(
    r: np.ndarray, v: np.ndarray, r_safe: float, brake_accel: float, gain: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Backup-barrier rows A a >= b for offsets r (K, 3) = p - o and velocity v (3,) (``barrier: backup``).

    docs/shield.md, "Backup barrier".

    The barrier h = D - r_safe, D the closest distance to the point over one backup maneuver shared by every
    point, braking straight along -v at a_b = ``brake_accel`` to a stop (``backup_distance``). Under that maneuver
    no D decreases, so the rows of all points hold together at a = -a_b v / |v| wherever every h >= 0: their
    intersection stays feasible, which per-point unions (``passing``) did not give. Its first-order row
    Ddot >= -gain h, with x, m, S and u of ``backup_distance`` and r_perp = r - (r.u) u (|r_perp| = m):
      0 < x < S:  Ddot = x (r_perp.a) / (m |v|),
      x >= S:     Ddot = [-(x - S)|v| - (x - S)(|v| / a_b) u.a + (S / |v|) r_perp.a] / D,
    written as 2 q.a >= b after multiplying by 2 a_b D / |v|, so that head-on (m = 0) A = 2 q = -2 (x - S) u is
    the braking barrier's normal 2 r. A straight flight past a point it misses by m >= r_safe meets its row at
    a = 0 once the stopping point is behind the point. Points behind the vehicle (x <= 0) give no row
    (A = 0, b = -inf); where h < 0 or |v| <= ``PASSING_MIN_SPEED`` the point takes its braking row
    (``braking_rows``), which pushes away from it. Returns (A (K, 3), b (K,), backup (K,) bool).
    """
    r = np.atleast_2d(np.asarray(r, dtype=np.float64))
    v = np.asarray(v, dtype=np.float64)
    a_mat, b = braking_rows(r, v, r_safe, brake_accel, gain)
    speed = float(np.linalg.norm(v))
    if speed <= PASSING_MIN_SPEED:
        return a_mat, b, np.zeros(len(r), dtype=bool)
    u = v / speed
    x = -(r @ u)
    r_perp = r + x[:, None] * u[None, :]
    stop = speed * speed / (2.0 * brake_accel)
    big_d = backup_distance(r, v, brake_accel)
    use = big_d >= r_safe
    behind = use & (x <= 0.0)
    beside = use & (x > 0.0) & (x < stop)
    ahead = use & (x >= stop)
    scale = 2.0 * brake_accel / speed  # row times 2 a_b D / |v|
    a_mat = a_mat.copy()
    b = b.copy()
    a_mat[behind], b[behind] = 0.0, -np.inf
    a_mat[beside] = (x[beside] / stop)[:, None] * r_perp[beside]
    b[beside] = -scale * gain * big_d[beside] * (big_d[beside] - r_safe)
    t = x[ahead] - stop
    a_mat[ahead] = -2.0 * t[:, None] * u[None, :] + r_perp[ahead]
    b[ahead] = 2.0 * brake_accel * t - scale * gain * big_d[ahead] * (big_d[ahead] - r_safe)
    return a_mat, b, use


def hocbf_rows(
    r: np.ndarray, v: np.ndarray, alpha0: float, alpha1: float, r_safe: float
) -> tuple[np.ndarray, np.ndarray]:
    """HOCBF constraint rows A a >= b for offsets r (K, 3) = p - o and velocity v (3,).

    A = 2 r^T,  b = -2|v|^2 - alpha1 Bdot - alpha0 B  with  B = |r|^2 - r_safe^2,  Bdot = 2 r.v.
    """
    b_val = np.sum(r * r, axis=1) - r_safe**2
    b_dot = 2.0 * r @ v
    return 2.0 * r, -2.0 * float(v @ v) - alpha1 * b_dot - alpha0 * b_val


# --------------------------------------------------------------------------------------------- constraint selection
@nb.njit(cache=True, nogil=True)
def _rhs(rx: float, ry: float, rz: float, v: np.ndarray, alpha0: float, alpha1: float, r_safe: float) -> float:
    """Right-hand side b of the row 2 r.a >= b: -2|v|^2 - alpha1 Bdot - alpha0 B, Bdot = 2 r.v, B = |r|^2 - r_safe^2."""
    return (
        -2.0 * (v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        - alpha1 * 2.0 * (rx * v[0] + ry * v[1] + rz * v[2])
        - alpha0 * (rx * rx + ry * ry + rz * rz - r_safe * r_safe)
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _brake_rhs(rx: float, ry: float, rz: float, vx: float, vy: float, vz: float, r_safe: float, a_b: float,
               gain: float, s_min: float) -> float:  # fmt: skip
    """Right-hand side 2 d b of the braking row 2 r.a >= 2 d b on scalars (see ``braking_rows``).

    ``s_min`` = sqrt(2 a_b BRAKE_EPS), the floor of the divisor s, computed once per call by ``_consts``.
    """
    return _brake_rhs_d(rx, ry, rz, math.sqrt(rx * rx + ry * ry + rz * rz), vx, vy, vz, r_safe, a_b, gain, s_min)


@nb.njit(cache=True, nogil=True, inline="always")
def _brake_rhs_d(rx: float, ry: float, rz: float, dist: float, vx: float, vy: float, vz: float, r_safe: float,
                 a_b: float, gain: float, s_min: float) -> float:  # fmt: skip
    """``_brake_rhs`` with |r| given (``dist``), for a caller that has computed it already."""
    d = max(dist, 1e-9)
    c = -(rx * vx + ry * vy + rz * vz) / d
    e = d - r_safe
    root = math.sqrt(2.0 * a_b * abs(e))
    s = max(root, s_min)  # one square root per point; the floor only for the division
    h = math.copysign(root, e) - c
    b = -gain * h + a_b * c / s - (vx * vx + vy * vy + vz * vz - c * c) / d
    return 2.0 * d * b


@nb.njit(cache=True, nogil=True, inline="always")
def _backup_row(rx: float, ry: float, rz: float, d: float, vx: float, vy: float, vz: float, speed: float,
                r_safe: float, a_b: float, gain: float) -> tuple[float, float, float, float]:  # fmt: skip
    """A point's backup-barrier row 2 q.a >= b on scalars (see ``backup_rows``), or NaNs where h < 0.

    A point behind (x <= 0) outside r_safe gives (0, 0, 0, -inf): nothing to constrain. Where h < 0 the caller
    takes the braking row instead. ``speed`` = |v| > 0, ``d`` = |r|.
    """
    ux, uy, uz = vx / speed, vy / speed, vz / speed
    x = -(rx * ux + ry * uy + rz * uz)  # how far ahead along v the point lies
    if x <= 0.0:
        if d >= r_safe:
            return 0.0, 0.0, 0.0, -np.inf
        return np.nan, np.nan, np.nan, np.nan
    px, py, pz = rx + x * ux, ry + x * uy, rz + x * uz  # r_perp = r - (r.u) u, (r.u = -x)
    m = math.sqrt(px * px + py * py + pz * pz)
    stop = speed * speed / (2.0 * a_b)
    if x < stop:  # the point is beside the stopping path: D = m
        if m < r_safe:
            return np.nan, np.nan, np.nan, np.nan
        w = 0.5 * x / stop
        return w * px, w * py, w * pz, -2.0 * a_b / speed * gain * m * (m - r_safe)
    t = x - stop
    big_d = math.sqrt(t * t + m * m)
    if big_d < r_safe:
        return np.nan, np.nan, np.nan, np.nan
    return (-t * ux + 0.5 * px, -t * uy + 0.5 * py, -t * uz + 0.5 * pz,
            2.0 * a_b * t - 2.0 * a_b / speed * gain * big_d * (big_d - r_safe))  # fmt: skip


@nb.njit(cache=True, nogil=True, inline="always")
def _point_row(rx: float, ry: float, rz: float, d: float, vx: float, vy: float, vz: float, speed: float, k: tuple
               ) -> tuple[float, float, float, float]:  # fmt: skip
    """A point's row 2 q.a >= b at offset r (``d`` = |r|) and velocity v (``speed`` = |v|) with the braking barrier.

    The braking row has q = r (``_brake_rhs_d``). With passing on (``k[20]``), the collision-cone barrier
    h_c = r.v + |v| S, S = sqrt(d^2 - r_safe^2), competes; its first-order row hdot_c >= -gain h_c is
    (r + S v / |v|).a >= -gain h_c - |v|^2 - |v| (r.v) / S, i.e. q = (r + S v / |v|) / 2. The safe set is the
    union {h_b >= 0} or {h_c >= 0}: holding either barrier that is non-negative keeps the point r_safe away. The
    cone row is taken where h_c >= 0 and either h_b < 0 or the cone row is the nearer to being met at the
    acceleration ``k[6:9]`` (its value over |A| larger); otherwise the braking row (``passing_rows``). With the
    backup barrier (``k[20]`` = 2) the point's backup row (``_backup_row``, ``backup_rows``), or its braking row
    where the backup barrier is negative.
    """
    if k[20] > 1.5 and speed > PASSING_MIN_SPEED:  # backup barrier
        qx, qy, qz, b_k = _backup_row(rx, ry, rz, d, vx, vy, vz, speed, k[16], k[17], k[18])
        if qx == qx:  # NaN: the backup barrier is negative, the braking row stands in
            return qx, qy, qz, b_k
    b = _brake_rhs_d(rx, ry, rz, d, vx, vy, vz, k[16], k[17], k[18], k[19])
    if 0.5 < k[20] < 1.5 and speed > PASSING_MIN_SPEED:
        s2 = d * d - k[16] * k[16]
        if s2 > PASSING_MIN_S * PASSING_MIN_S:
            rv = rx * vx + ry * vy + rz * vz
            s = math.sqrt(s2)
            h_c = rv + speed * s
            if h_c >= 0.0:
                w = s / speed
                cx, cy, cz = rx + w * vx, ry + w * vy, rz + w * vz
                b_c = -k[18] * h_c - speed * speed - speed * rv / s
                e = d - k[16]
                take = e <= 0.0 or math.sqrt(2.0 * k[17] * e) + rv / d < 0.0  # h_b < 0
                if not take:  # both barriers hold: the row the acceleration is nearer to meeting
                    m_c = (cx * k[6] + cy * k[7] + cz * k[8] - b_c) / max(math.sqrt(cx * cx + cy * cy + cz * cz), 1e-12)
                    m_b = (2.0 * (rx * k[6] + ry * k[7] + rz * k[8]) - b) / (2.0 * d)
                    take = m_c > m_b
                if take:
                    return 0.5 * cx, 0.5 * cy, 0.5 * cz, b_c
    return rx, ry, rz, b


@nb.njit(cache=True, nogil=True, inline="always")
def _braking_point_rows(ox: float, oy: float, oz: float, rx: float, ry: float, rz: float, d: float, k: tuple,
                        use_lag: bool) -> tuple[float, float, float, float, float, float, float, float]:  # fmt: skip
    """A point's braking-barrier rows, which do not depend on the acceleration.

    (q0, b0) of its row now (``_point_row``; q0 = r for a braking row, ``d`` = |r|), and (q1, b1) of its row at
    the lagged state, or (0, 0, 0, -inf) where that row does not compete (no lag, or the prediction has passed the
    point: (p_lag - o).(p - o) <= 0). ``k`` holds the constants of ``_consts``.
    """
    q0x, q0y, q0z, b0 = _point_row(rx, ry, rz, d, k[0], k[1], k[2], k[21], k)
    if use_lag:
        qx, qy, qz = k[3] - ox, k[4] - oy, k[5] - oz
        if qx * rx + qy * ry + qz * rz > 0.0:
            dq = math.sqrt(qx * qx + qy * qy + qz * qz)
            q1x, q1y, q1z, b1 = _point_row(qx, qy, qz, dq, k[9], k[10], k[11], k[22], k)
            return q0x, q0y, q0z, b0, q1x, q1y, q1z, b1
    return q0x, q0y, q0z, b0, 0.0, 0.0, 0.0, -np.inf


@nb.njit(cache=True, nogil=True, inline="always")
def _pair_margin(rx: float, ry: float, rz: float, b0: float, qx: float, qy: float, qz: float, b1: float, ax: float,
                 ay: float, az: float) -> tuple[float, bool]:  # fmt: skip
    """The smaller row value at a of a point's two rows 2 r.a >= b0 and 2 q.a >= b1, and whether it is the second.

    (r is the first row's half-normal: the offset p - o for a braking row, see ``_point_row``.)

    The second wins only if strictly smaller; a row (0, -inf) never does.
    """
    m = 2.0 * (rx * ax + ry * ay + rz * az) - b0
    m_lag = 2.0 * (qx * ax + qy * ay + qz * az) - b1
    if m_lag < m:
        return m_lag, True
    return m, False


@nb.njit(cache=True, nogil=True, inline="always")
def _margin(rx: float, ry: float, rz: float, vx: float, vy: float, vz: float, ax: float, ay: float, az: float,
            vv2: float, alpha0: float, alpha1: float, rs2: float) -> float:  # fmt: skip
    """HOCBF row value 2 r.a + 2|v|^2 + alpha1 (2 r.v) + alpha0 (|r|^2 - r_safe^2) (negative: violated).

    On scalars, with vv2 = 2|v|^2 and rs2 = r_safe^2 given.
    """
    return (
        2.0 * (rx * ax + ry * ay + rz * az)
        + vv2
        + alpha1 * 2.0 * (rx * vx + ry * vy + rz * vz)
        + alpha0 * (rx * rx + ry * ry + rz * rz - rs2)
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _tighter_margin(ox: float, oy: float, oz: float, rx: float, ry: float, rz: float, k: tuple,
                    use_lag: bool, alpha0: float, alpha1: float) -> tuple[float, bool]:  # fmt: skip
    """Margin of point o = (ox, oy, oz) (r = p - o given) and whether its row at the lagged state is the tighter one.

    ``k`` holds the per-call constants unpacked by ``_consts``. With ``use_lag`` the row at (p_lag, v_lag) competes
    unless that prediction has passed the point ((p_lag - o).(p - o) <= 0, where its row would push towards it).
    Scalars and an inlined body: a per-point call that passes arrays costs their reference counts, several times
    the arithmetic.
    """
    if k[15] > 0.5:  # braking
        q0x, q0y, q0z, b0, qx, qy, qz, b1 = _braking_point_rows(
            ox, oy, oz, rx, ry, rz, math.sqrt(rx * rx + ry * ry + rz * rz), k, use_lag
        )
        return _pair_margin(q0x, q0y, q0z, b0, qx, qy, qz, b1, k[6], k[7], k[8])
    m = _margin(rx, ry, rz, k[0], k[1], k[2], k[6], k[7], k[8], k[12], alpha0, alpha1, k[14])
    if use_lag:
        qx, qy, qz = k[3] - ox, k[4] - oy, k[5] - oz
        if qx * rx + qy * ry + qz * rz > 0.0:
            m_lag = _margin(qx, qy, qz, k[9], k[10], k[11], k[6], k[7], k[8], k[13], alpha0, alpha1, k[14])
            if m_lag < m:
                return m_lag, True
    return m, False


@nb.njit(cache=True, nogil=True, inline="always")
def _consts(v: np.ndarray, p_lag: np.ndarray, a: np.ndarray, v_lag: np.ndarray, r_safe: float,
            brake: np.ndarray) -> tuple:  # fmt: skip
    """The per-call constants of ``_tighter_margin`` as a tuple (a value: passing it per point costs nothing).

    v (3), p_lag (3), a (3), v_lag (3), 2|v|^2, 2|v_lag|^2, r_safe^2, then the barrier: ``brake`` = (braking flag,
    brake_accel, gain, mode) with the flag > 0.5 for braking-type rows and the mode 0 / 1 / 2 for the braking
    barrier, its collision-cone union and the backup barrier (``_point_row``), r_safe, the braking divisor's floor
    sqrt(2 brake_accel BRAKE_EPS), the mode, |v| and
    |v_lag|.
    """
    return (v[0], v[1], v[2], p_lag[0], p_lag[1], p_lag[2], a[0], a[1], a[2], v_lag[0], v_lag[1], v_lag[2],
            2.0 * (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]),
            2.0 * (v_lag[0] * v_lag[0] + v_lag[1] * v_lag[1] + v_lag[2] * v_lag[2]), r_safe * r_safe,
            brake[0], r_safe, brake[1], brake[2], math.sqrt(2.0 * brake[1] * BRAKE_EPS), brake[3],
            math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]),
            math.sqrt(v_lag[0] * v_lag[0] + v_lag[1] * v_lag[1] + v_lag[2] * v_lag[2]))  # fmt: skip


@nb.njit(cache=True, nogil=True)
def _min_margin(
    points: np.ndarray,
    p: np.ndarray,
    v: np.ndarray,
    p_lag: np.ndarray,
    v_lag: np.ndarray,
    use_lag: bool,
    a: np.ndarray,
    alpha0: float,
    alpha1: float,
    r_safe: float,
    d_min: float,
    d_max: float,
    z_lo: float,
    z_hi: float,
    out_row: np.ndarray,
    brake: np.ndarray,
) -> float:
    """The smallest row value at acceleration ``a`` over every point ``_select`` considers, and that row.

    Same rules as ``_select`` (distance and height windows; with ``use_lag`` the tighter of a point's two rows
    unless the prediction passed it), without the binning: the active-set check. ``out_row`` gets (q_x, q_y, q_z,
    b) of the tightest row (A = 2 q; q = r except for a collision-cone row, ``_point_row``), the one a violated
    check adds to the QP.
    """
    best = np.inf
    best_i = -1
    best_lag = False
    k = _consts(v, p_lag, a, v_lag, r_safe, brake)
    for i in range(points.shape[0]):
        rx = p[0] - points[i, 0]
        ry = p[1] - points[i, 1]
        rz = p[2] - points[i, 2]
        d2 = rx * rx + ry * ry + rz * rz
        if d2 < d_min * d_min or d2 > d_max * d_max or points[i, 2] < z_lo or points[i, 2] > z_hi:
            continue
        m, lagged = _tighter_margin(points[i, 0], points[i, 1], points[i, 2], rx, ry, rz, k, use_lag, alpha0, alpha1)
        if m < best:
            best, best_i, best_lag = m, i, lagged
    if best_i >= 0:
        ox, oy, oz = points[best_i, 0], points[best_i, 1], points[best_i, 2]
        if k[15] > 0.5:  # braking: the point's rows again, the chosen one out
            rx, ry, rz = p[0] - ox, p[1] - oy, p[2] - oz
            q0x, q0y, q0z, b0, q1x, q1y, q1z, b1 = _braking_point_rows(
                ox, oy, oz, rx, ry, rz, math.sqrt(rx * rx + ry * ry + rz * rz), k, use_lag)  # fmt: skip
            if best_lag:
                out_row[0], out_row[1], out_row[2], out_row[3] = q1x, q1y, q1z, b1
            else:
                out_row[0], out_row[1], out_row[2], out_row[3] = q0x, q0y, q0z, b0
        else:
            ps, vs = (p_lag, v_lag) if best_lag else (p, v)
            rx, ry, rz = ps[0] - ox, ps[1] - oy, ps[2] - oz
            out_row[0], out_row[1], out_row[2] = rx, ry, rz
            out_row[3] = _rhs(rx, ry, rz, vs, alpha0, alpha1, r_safe)
    return best


@nb.njit(cache=True, nogil=True)
def _select(
    points: np.ndarray,
    p: np.ndarray,
    v: np.ndarray,
    p_lag: np.ndarray,
    v_lag: np.ndarray,
    use_lag: bool,
    a_raw: np.ndarray,
    alpha0: float,
    alpha1: float,
    r_safe: float,
    d_min: float,
    d_max: float,
    z_lo: float,
    z_hi: float,
    n_az: int,
    n_el: int,
    k_max: int,
    out_r: np.ndarray,
    out_b: np.ndarray,
    out_min: np.ndarray,
    out_o: np.ndarray,
    brake: np.ndarray,
    rows: np.ndarray,
    out_rows: np.ndarray,
) -> int:
    """Closest-in-constraint-terms point per direction sector, then the k_max tightest sectors.

    For each point o: r = p - o, margin m = 2 r.a_raw + 2|v|^2 + alpha1 (2 r.v) + alpha0 (|r|^2 - r_safe^2),
    i.e. how much the raw command satisfies that point's HOCBF row (negative = violated). With ``use_lag`` each
    point has a second row, the same barrier at the state predicted one lag ahead (p_lag, v_lag; ``lag_s``), unless
    that prediction has passed the point ((p_lag - o).(p - o) <= 0, where its row would push towards it); the point
    competes with its tighter row. Points are binned by the azimuth/elevation of o - p (``sectors.exact_sector``,
    computed by ``sectors.sector``); each bin keeps its smallest
    margin, and the k_max smallest bins are written to out_r (k_max, 3) in increasing margin order, with their
    HOCBF right-hand sides b (see ``hocbf_rows``) in out_b, and the smallest margin in out_min[0] (negative: the
    raw command violates a selected row, so the shield must act), and the selected points in out_o. Returns how
    many were written.

    With the braking barrier, every considered point's rows are also written to ``rows`` (at least one row per
    point): (r, b) of its row at the current state and (q, b_lag) of its row at the lagged state, or (0, -inf) where
    that row does not compete; ``out_rows[0]`` gets their count. The braking rows' b does not depend on the
    acceleration, so the active-set check at another acceleration (``_rows_min_margin``) reads them instead of
    recomputing two square roots per point.
    """
    n_sec = n_az * n_el
    best_m = np.full(n_sec, np.inf)
    best_i = np.full(n_sec, -1)
    best_lag = np.zeros(n_sec, dtype=np.bool_)
    best_row = np.full(n_sec, -1)
    el_bounds = elevation_bounds(n_el)
    k = _consts(v, p_lag, a_raw, v_lag, r_safe, brake)
    braking = k[15] > 0.5
    nr = 0
    for i in range(points.shape[0]):
        rx = p[0] - points[i, 0]
        ry = p[1] - points[i, 1]
        rz = p[2] - points[i, 2]
        d2 = rx * rx + ry * ry + rz * rz
        if d2 < d_min * d_min or d2 > d_max * d_max or points[i, 2] < z_lo or points[i, 2] > z_hi:
            continue
        d = math.sqrt(d2)
        if braking:  # _tighter_margin's braking branch, keeping the rows for the active-set check
            q0x, q0y, q0z, b0, qx, qy, qz, b1 = _braking_point_rows(points[i, 0], points[i, 1], points[i, 2], rx, ry,
                                                                    rz, d, k, use_lag)  # fmt: skip
            m, lagged = _pair_margin(q0x, q0y, q0z, b0, qx, qy, qz, b1, k[6], k[7], k[8])
            rows[nr, 0], rows[nr, 1], rows[nr, 2], rows[nr, 3] = q0x, q0y, q0z, b0
            rows[nr, 4], rows[nr, 5], rows[nr, 6], rows[nr, 7] = qx, qy, qz, b1
            nr += 1
        else:
            m, lagged = _tighter_margin(points[i, 0], points[i, 1], points[i, 2], rx, ry, rz, k, use_lag, alpha0,
                                        alpha1)  # fmt: skip
        s = sector(rx, ry, rz, d, n_az, n_el, el_bounds)  # exact_sector's integer, mostly without atan2 / asin
        if m < best_m[s]:
            best_m[s] = m
            best_i[s] = i
            best_lag[s] = lagged
            best_row[s] = nr - 1
    order = np.argsort(best_m)
    out_min[0] = best_m[order[0]]
    n = 0
    for j in range(min(k_max, n_sec)):
        s = order[j]
        if best_i[s] < 0:
            break
        i = best_i[s]
        if braking:  # the row kept for the point
            j, row = (4 if best_lag[s] else 0), best_row[s]
            out_r[n, 0], out_r[n, 1], out_r[n, 2], out_b[n] = rows[row, j], rows[row, j + 1], rows[row, j + 2], rows[
                row, j + 3]  # fmt: skip
        else:
            ps, vs = (p_lag, v_lag) if best_lag[s] else (p, v)
            rx, ry, rz = ps[0] - points[i, 0], ps[1] - points[i, 1], ps[2] - points[i, 2]
            out_r[n, 0], out_r[n, 1], out_r[n, 2] = rx, ry, rz
            out_b[n] = _rhs(rx, ry, rz, vs, alpha0, alpha1, r_safe)
        out_o[n, 0], out_o[n, 1], out_o[n, 2] = points[i, 0], points[i, 1], points[i, 2]
        n += 1
    out_rows[0] = nr if braking else -1
    return n


@nb.njit(cache=True, nogil=True)
def _rows_min_margin(rows: np.ndarray, n: int, a: np.ndarray, out_row: np.ndarray) -> float:
    """``_min_margin`` from the braking rows ``_select`` kept (``rows[:n]``): the smallest row value at ``a``.

    Each point competes with the smaller of its two rows (the lagged one only if strictly smaller), as in
    ``_min_margin``, so the result and ``out_row`` (r, b of the tightest row) are the same numbers.
    """
    best = np.inf
    best_i = -1
    best_lag = False
    ax, ay, az = a[0], a[1], a[2]
    for i in range(n):
        m, lagged = _pair_margin(rows[i, 0], rows[i, 1], rows[i, 2], rows[i, 3], rows[i, 4], rows[i, 5], rows[i, 6],
                                 rows[i, 7], ax, ay, az)  # fmt: skip
        if m < best:
            best, best_i, best_lag = m, i, lagged
    if best_i >= 0:
        j = 4 if best_lag else 0
        out_row[0], out_row[1], out_row[2], out_row[3] = (rows[best_i, j], rows[best_i, j + 1], rows[best_i, j + 2],
                                                          rows[best_i, j + 3])  # fmt: skip
    return best
