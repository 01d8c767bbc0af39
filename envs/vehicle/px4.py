"""A batched PX4-style multicopter inner loop: attitude control, rate control and control allocation.

The structure follows PX4's ``mc_att_control`` (reduced-attitude quaternion control that prioritises roll and
pitch over yaw), ``mc_rate_control`` (PID on body rates with anti-windup and the derivative on the measured
angular acceleration) and ``control_allocator`` (effectiveness-matrix pseudo-inverse with sequential
desaturation). It is our own implementation of those published algorithms, vectorised over N vehicles with
numpy (the attitude loop's arithmetic in two numba kernels, bit for bit its numpy formulation): no per-vehicle Python
loop. Shapes are stated as (N, ...). Body frame is FLU, quaternions (w, x, y, z).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from envs.vehicle.config import ControllerConfig, VehicleConfig
from envs.vehicle.rotations import attitude_from_thrust_axis, euler_zyx_to_rot, quat_mul_scalars, rot_to_quat

# ---------------------------------------------------------------------------------------------------------------
# Geometry of the X quadrotor (PX4 motor numbering), FLU body frame.
# Motor 1 front-right CCW, 2 back-left CCW, 3 front-left CW, 4 back-right CW (seen from above).
# ---------------------------------------------------------------------------------------------------------------
_MOTOR_DIRS_XY = np.array([[1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [-1.0, -1.0]]) / math.sqrt(2.0)
MOTOR_SPIN = np.array([1.0, 1.0, -1.0, -1.0])
"""+1 for a rotor spinning counter-clockwise seen from above. Its reaction torque on the body is -s * k_m/k_f * T."""


def motor_positions(arm_length: float) -> np.ndarray:
    """Rotor positions in the body frame, shape (4, 3) [m]."""
    xy = _MOTOR_DIRS_XY * arm_length
    return np.concatenate((xy, np.zeros((4, 1))), axis=1)


def effectiveness(arm_length: float, moment_ratio: float) -> np.ndarray:
    """Effectiveness matrix B (4, 4): per-motor thrusts T [N] -> [F_z, tau_x, tau_y, tau_z] in N and N m.

    Row 0: F_z = sum T_i. Rows 1-2: tau = r_i x (0, 0, T_i) = (y_i T_i, -x_i T_i). Row 3: tau_z = -s_i k T_i.
    """
    p = motor_positions(arm_length)
    return np.stack((np.ones(4), p[:, 1], -p[:, 0], -MOTOR_SPIN * moment_ratio))


class Allocator:
    """PX4-style control allocation from [collective thrust, normalised torques] to normalised motor thrusts.

    Motor commands are u = T / T_max in [u_min, 1]. The mix M = B_u^+ (B_u = B * T_max, the effectiveness in
    u-units) has its torque columns normalised as PX4's ``ControlAllocationPseudoInverse`` does: roll and pitch
    share the scale sqrt(|m_col|^2 / (n_nonzero / 2)), yaw is scaled by its largest coefficient. So a normalised
    roll torque of 1 moves each motor by +-1/sqrt(2) and a yaw torque of 1 moves each by +-1.

    Saturation follows PX4's priorities (MC_AIRMODE=0 by default): roll/pitch first, then collective thrust (only
    lowered to make room, or also raised with airmode), then yaw with whatever authority is left. The torque that
    could not be allocated is reported per axis as saturation flags for the rate integrator's anti-windup.
    """

    def __init__(self, cfg: VehicleConfig) -> None:  # noqa: D107
        self.t_max = cfg.max_motor_thrust
        self.u_min = cfg.motor.min_thrust_fraction
        self.airmode = cfg.controller.airmode
        b_u = effectiveness(cfg.airframe.arm_length, cfg.motor.moment_ratio) * self.t_max
        mix = np.linalg.pinv(b_u)  # (4 motors, 4 axes [F, tx, ty, tz])
        scale = np.ones(4)
        rp = [
            math.sqrt(float(mix[:, i] @ mix[:, i]) / (np.count_nonzero(np.abs(mix[:, i]) > 1e-9) / 2.0)) for i in (1, 2)
        ]
        scale[1] = scale[2] = max(rp)
        scale[3] = float(np.max(mix[:, 3]))
        self.mix = mix / scale  # columns: thrust [N], roll, pitch, yaw [normalised]
        self.torque_scale = 1.0 / scale[1:]
        """Physical torque [N m] per unit of normalised torque, for roll, pitch, yaw."""
        self.effectiveness_n = np.linalg.pinv(self.mix)  # u -> [F, roll_n, pitch_n, yaw_n]
        if not np.allclose(self.mix[:, 0], self.mix[0, 0]):
            raise ValueError("the allocator assumes a symmetric X quadrotor (uniform thrust column)")

    def allocate(self, thrust: np.ndarray, torque_n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Map collective thrust (N,) [N] and normalised torques (N, 3) to motor commands.

        With t the common (collective) motor level and rp the roll/pitch part of the mix (both in u-units):

        1. If the roll/pitch spread max(rp) - min(rp) exceeds the range 1 - u_min, scale rp down to fit.
        2. Upper saturation: lower t to 1 - max(rp) (thrust is sacrificed for attitude, as in PX4).
        3. Lower saturation: with airmode, raise t to u_min - min(rp); without it (PX4 default) shrink rp instead,
           so the thrust is never raised above the command.
        4. Yaw y = tau_z * m_yaw is added scaled by the largest k in [0, 1] keeping every motor in range.

        Returns:
            u: normalised motor thrusts (N, 4) in [u_min, 1].
            sat_pos: (N, 3) bool, True where an axis got less positive torque than asked (anti-windup).
            sat_neg: (N, 3) bool, likewise for negative torque.
        """
        m = self.mix
        lo, hi = self.u_min, 1.0
        t = (thrust * m[0, 0])[:, None]  # (N, 1): the thrust column is uniform for the symmetric X quad
        rp = torque_n[:, 0:1] * m[:, 1] + torque_n[:, 1:2] * m[:, 2]  # (N, 4)
        spread = rp.max(axis=1, keepdims=True) - rp.min(axis=1, keepdims=True)
        rp = rp * np.minimum(1.0, (hi - lo) / np.maximum(spread, 1e-12))
        t = np.minimum(t, hi - rp.max(axis=1, keepdims=True))
        rp_min = rp.min(axis=1, keepdims=True)
        if self.airmode:
            t = np.maximum(t, lo - rp_min)
        else:
            t = np.maximum(t, lo)
            short = t + rp_min < lo
            s = np.where(short, (t - lo) / np.maximum(-rp_min, 1e-12), 1.0)
            rp = rp * np.clip(s, 0.0, 1.0)
        u = t + rp
        # Yaw gets the authority that is left: largest k in [0, 1] with lo <= u + k y <= hi for every motor.
        y = torque_n[:, 2:3] * m[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            k_up = np.where(y > 1e-12, (hi - u) / y, np.inf)
            k_dn = np.where(y < -1e-12, (lo - u) / y, np.inf)
        k = np.clip(np.minimum(k_up, k_dn).min(axis=1, keepdims=True), 0.0, 1.0)
        u = np.clip(u + k * y, lo, hi)
        # Anti-windup flags: torque asked minus torque achieved (normalised units).
        unalloc = torque_n - u @ self.effectiveness_n[1:].T
        return u, unalloc > 1e-3, unalloc < -1e-3


@numba.njit(cache=True, fastmath=False)
def _reduced_attitude_kernel(q: np.ndarray, q_sp: np.ndarray, q_red: np.ndarray, q_mix: np.ndarray) -> None:
    """Steps 1-2 of :meth:`AttitudeRateController.attitude` before its arccos / arcsin: ``q_red`` and ``q_mix``.

    Every product, sum and square root in the numpy formulation's order (``np.sum`` and ``np.linalg.norm`` reduce
    left to right over 3 and 4 items, ``np.cross`` as ``a1 b2 - a2 b1``, ...), no fused multiply-add, so the result is
    the numpy formulation's to the bit (tests/envs/test_vehicle.py).
    """
    for i in range(q.shape[0]):
        w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        ws, xs, ys, zs = q_sp[i, 0], q_sp[i, 1], q_sp[i, 2], q_sp[i, 3]
        # Thrust axes: the third columns of the rotation matrices (quat_to_rot's expressions).
        a0, a1, a2 = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)
        b0, b1, b2 = 2.0 * (xs * zs + ws * ys), 2.0 * (ys * zs - ws * xs), 1.0 - 2.0 * (xs * xs + ys * ys)
        r0 = 1.0 + (a0 * b0 + a1 * b1 + a2 * b2)
        r1 = a1 * b2 - a2 * b1
        r2 = a2 * b0 - a0 * b2
        r3 = a0 * b1 - a1 * b0
        n = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
        if n < 1e-6:  # antiparallel: the full setpoint
            rw, rx, ry, rz = ws, xs, ys, zs
        else:
            d = max(n, 1e-12)
            r0, r1, r2, r3 = r0 / d, r1 / d, r2 / d, r3 / d
            rw, rx, ry, rz = quat_mul_scalars(r0, r1, r2, r3, w, x, y, z)
        q_red[i, 0], q_red[i, 1], q_red[i, 2], q_red[i, 3] = rw, rx, ry, rz
        cw, cx, cy, cz = rw, -rx, -ry, -rz  # conjugate
        mw, mx, my, mz = quat_mul_scalars(cw, cx, cy, cz, ws, xs, ys, zs)
        if mw < 0.0:
            mw, mx, my, mz = -mw, -mx, -my, -mz
        q_mix[i, 0], q_mix[i, 1], q_mix[i, 2], q_mix[i, 3] = mw, mx, my, mz


@numba.njit(cache=True, fastmath=False)
def _attitude_error_kernel(
    q: np.ndarray,
    q_red: np.ndarray,
    cos_w: np.ndarray,
    sin_z: np.ndarray,
    gain: np.ndarray,
    limit: np.ndarray,
    out: np.ndarray,
) -> None:
    """Step 3 of :meth:`AttitudeRateController.attitude`: rate setpoints from ``q_red`` and the yaw quaternion.

    The yaw quaternion is ``(cos_w, 0, 0, sin_z)``; the numpy formulation's order, its zeros multiplied as it did.
    """
    for i in range(q.shape[0]):
        dw, dx, dy, dz = quat_mul_scalars(
            q_red[i, 0], q_red[i, 1], q_red[i, 2], q_red[i, 3], cos_w[i], 0.0, 0.0, sin_z[i]
        )
        ew, ex, ey, ez = quat_mul_scalars(q[i, 0], -q[i, 1], -q[i, 2], -q[i, 3], dw, dx, dy, dz)
        sign = 2.0 * (-1.0 if ew < 0.0 else 1.0)
        e = (sign * ex, sign * ey, sign * ez)
        for k in range(3):
            v = gain[i, k] * e[k]
            if v < -limit[k]:  # np.clip's order: the lower bound, then the upper; NaN stays NaN
                v = -limit[k]
            if v > limit[k]:
                v = limit[k]
            out[i, k] = v


class AttitudeRateController:
    """PX4-style attitude P loop and rate PID, batched over N vehicles with per-vehicle gains.

    Gains are (N, 3) arrays (``attitude_p``, ``rate_p``, ``rate_i``, ``rate_d``), so domain randomisation can
    perturb them per vehicle. State: rate integrator (N, 3), previous body rate (N, 3), filtered angular
    acceleration (N, 3).
    """

    def __init__(self, num: int, cfg: ControllerConfig, dt: float) -> None:  # noqa: D107
        self.num = num
        self.cfg = cfg
        self.dt = dt
        ones = np.ones((num, 1))
        # PX4 compensates the yaw weight's rescaling of the yaw error by dividing the yaw gain by the weight.
        att_p = np.array(cfg.attitude_p, dtype=float)
        if cfg.yaw_weight > 1e-4:
            att_p[2] /= cfg.yaw_weight
        self.attitude_p = ones * att_p
        self.rate_p = ones * np.array(cfg.rate_p)
        self.rate_i = ones * np.array(cfg.rate_i)
        self.rate_d = ones * np.array(cfg.rate_d)
        self.yaw_weight = cfg.yaw_weight
        self.rate_limit = np.deg2rad(np.array(cfg.max_rate_deg))
        self.int_limit = np.array(cfg.rate_integrator_limit)
        # First-order low-pass on the differentiated gyro: alpha = 1 - exp(-2 pi fc dt).
        self.dgyro_alpha = 1.0 - math.exp(-2.0 * math.pi * cfg.dgyro_cutoff_hz * dt)
        self.rate_int_buf = np.zeros((num, 3))
        self.prev_rate_buf = np.zeros((num, 3))
        self.ang_acc_buf = np.zeros((num, 3))
        self.sat_pos_buf = np.zeros((num, 3), dtype=bool)
        self.sat_neg_buf = np.zeros((num, 3), dtype=bool)

    def reset(self, env_ids: np.ndarray, rate_b: np.ndarray | None = None) -> None:
        """Zero the integrator and filters of ``env_ids``; seed the derivative with the current rates (M, 3)."""
        self.rate_int_buf[env_ids] = 0.0
        self.ang_acc_buf[env_ids] = 0.0
        self.prev_rate_buf[env_ids] = 0.0 if rate_b is None else rate_b
        self.sat_pos_buf[env_ids] = False
        self.sat_neg_buf[env_ids] = False

    def attitude(self, quat_wb: np.ndarray, quat_sp: np.ndarray) -> np.ndarray:
        """Reduced-attitude quaternion P control (PX4 ``AttitudeControl::update``). Returns rate setpoints (N, 3).

        1. q_red: the shortest rotation taking the current thrust axis e_z to the desired one e_z_d, applied to q
           (roll/pitch only). 2. Re-admit the remaining yaw rotation scaled by the yaw weight w:
           q_mix = q_red^-1 q_sp, q_d = q_red (cos(w acos q_mix.w), 0, 0, sin(w asin q_mix.z)).
        3. Error q_e = q^-1 q_d, e = 2 sign(q_e.w) q_e.xyz (sin(angle/2)-scaled axis), rate_sp = K_p * e, clipped.
        """
        q = np.ascontiguousarray(quat_wb, dtype=np.float64)
        q_sp = np.ascontiguousarray(quat_sp, dtype=np.float64)
        q_red = np.empty_like(q)
        q_mix = np.empty_like(q)
        _reduced_attitude_kernel(q, q_sp, q_red, q_mix)
        w = self.yaw_weight
        half_w = w * np.arccos(np.clip(q_mix[:, 0], -1.0, 1.0))
        half_z = w * np.arcsin(np.clip(q_mix[:, 3], -1.0, 1.0))
        out = np.empty((q.shape[0], 3))
        _attitude_error_kernel(q, q_red, np.cos(half_w), np.sin(half_z), np.ascontiguousarray(self.attitude_p),
                               np.ascontiguousarray(self.rate_limit, dtype=np.float64), out)  # fmt: skip
        return out

    def rate(self, rate_sp: np.ndarray, rate_b: np.ndarray) -> np.ndarray:
        """Rate PID (PX4 ``RateControl::update``). Returns normalised torques (N, 3) in [-1, 1].

        torque = P * (rate_sp - rate) + I_state - D * d(rate)/dt   (derivative on measurement, low-passed)
        The integrator uses PX4's anti-windup: no growth in a saturated direction, a factor
        max(0, 1 - (e / 400 deg/s)^2) that slows integration for large errors, and a hard limit.
        """
        # Angular acceleration estimate: filtered backward difference of the measured rate.
        raw_acc = (rate_b - self.prev_rate_buf) / self.dt
        self.ang_acc_buf += self.dgyro_alpha * (raw_acc - self.ang_acc_buf)
        self.prev_rate_buf[:] = rate_b
        err = rate_sp - rate_b
        torque = self.rate_p * err + self.rate_int_buf - self.rate_d * self.ang_acc_buf
        # Integrator update (after computing the output, as PX4 does).
        i_err = np.where(self.sat_pos_buf, np.minimum(err, 0.0), err)
        i_err = np.where(self.sat_neg_buf, np.maximum(i_err, 0.0), i_err)
        i_factor = np.maximum(0.0, 1.0 - (i_err / math.radians(400.0)) ** 2)
        self.rate_int_buf = np.clip(
            self.rate_int_buf + i_factor * self.rate_i * i_err * self.dt, -self.int_limit, self.int_limit
        )
        return np.clip(torque, -1.0, 1.0)


def attitude_setpoint(command: np.ndarray, cfg: ControllerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Clamp a command batch and turn it into (collective thrust [m/s^2] (N,), attitude setpoint quaternion (N, 4)).

    ``command`` is (N, 4) = [f_n, phi_ref, theta_ref, psi_ref] with ZYX Euler angles in rad. f_n is clamped to
    ``thrust_range``; roll and pitch each to +-max_tilt, then the thrust axis z_d = R(phi, theta, psi) e3 is
    rotated towards vertical if its tilt still exceeds max_tilt (PX4 limits the tilt of the thrust vector), and
    the attitude is rebuilt from (z_d, psi) as PX4's ``bodyzToAttitude`` does.
    """
    max_tilt = math.radians(cfg.max_tilt_deg)
    f_n = np.clip(command[:, 0], *cfg.thrust_range)
    phi = np.clip(command[:, 1], -max_tilt, max_tilt)
    theta = np.clip(command[:, 2], -max_tilt, max_tilt)
    psi = command[:, 3]
    z_d = euler_zyx_to_rot(phi, theta, psi)[:, :, 2]
    # Tilt limit: keep the horizontal direction, set the angle to max_tilt.
    cos_tilt = z_d[:, 2]
    over = cos_tilt < math.cos(max_tilt)
    if np.any(over):
        h = z_d[over, :2]
        h = h / np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
        z_d[over, :2] = h * math.sin(max_tilt)
        z_d[over, 2] = math.cos(max_tilt)
    q_sp = rot_to_quat(attitude_from_thrust_axis(z_d, psi))
    return f_n, q_sp
