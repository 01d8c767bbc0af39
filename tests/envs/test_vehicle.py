"""The simulated quadrotor and its PX4-style inner loop: closed-loop behaviour on the real MuJoCo model."""

import math

import mujoco
import numpy as np
import pytest

from envs.config import ConfigError, load_config
from envs.vehicle.config import VehicleConfig
from envs.vehicle.px4 import Allocator, AttitudeRateController, attitude_setpoint, effectiveness
from envs.vehicle.response import attitude_step, hover_hold, tilt_acceleration
from envs.vehicle.rotations import euler_zyx_to_rot, quat_conj, quat_mul, quat_to_rot, rot_to_euler_zyx, rot_to_quat
from envs.vehicle.vehicles import Vehicles

G = 9.81


# ----------------------------------------------------------------------------- rotations
def test_quat_to_rot_matches_mujoco():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ours = quat_to_rot(q)
    for i in range(len(q)):
        ref = np.zeros(9)
        mujoco.mju_quat2Mat(ref, q[i])
        np.testing.assert_allclose(ours[i], ref.reshape(3, 3), atol=1e-12)
    back = rot_to_quat(ours)
    q_canon = np.where(q[:, :1] < 0, -q, q)
    np.testing.assert_allclose(back, q_canon, atol=1e-9)


def _quat_mul_numpy(q, p):
    w1, x1, y1, z1 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    w2, x2, y2, z2 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    w = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    x = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    y = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    return np.stack((w, x, y, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2), axis=-1)


def _quat_to_rot_numpy(q):
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))  # fmt: skip
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def test_quaternion_kernels_equal_the_numpy_expressions_to_the_bit():
    """The compiled Hamilton product and rotation matrix (float64) against the numpy expressions they replace (the
    physics must fly the same to the bit): random, non-unit, strided and batched (2, 5, 4) inputs; float32 input
    keeps numpy's float32 arithmetic (stored as float64, as before)."""
    rng = np.random.default_rng(7)
    q = rng.normal(size=(257, 4))
    p = rng.normal(size=(257, 4)) * 3.0
    np.testing.assert_array_equal(quat_mul(q, p), _quat_mul_numpy(q, p))
    np.testing.assert_array_equal(quat_to_rot(q), _quat_to_rot_numpy(q))
    strided = rng.normal(size=(40, 8))[:, ::2]
    np.testing.assert_array_equal(quat_to_rot(strided), _quat_to_rot_numpy(strided))
    np.testing.assert_array_equal(quat_mul(strided, q[:40]), _quat_mul_numpy(strided, q[:40]))
    batch = rng.normal(size=(2, 5, 4))
    assert quat_to_rot(batch).shape == (2, 5, 3, 3)
    np.testing.assert_array_equal(quat_to_rot(batch), _quat_to_rot_numpy(batch))
    np.testing.assert_array_equal(quat_mul(batch, batch[::-1]), _quat_mul_numpy(batch, batch[::-1]))
    q32 = q.astype(np.float32)
    np.testing.assert_array_equal(quat_to_rot(q32), _quat_to_rot_numpy(q32).astype(np.float64))
    assert not np.array_equal(quat_to_rot(q32), _quat_to_rot_numpy(q32.astype(np.float64)))
    # Broadcasting shapes take the numpy path: one quaternion times many.
    np.testing.assert_array_equal(quat_mul(q[:1], p), _quat_mul_numpy(q[:1], p))
    # By hand: i * j = k, and the identity's matrix.
    np.testing.assert_array_equal(quat_mul(np.array([[0.0, 1, 0, 0]]), np.array([[0.0, 0, 1, 0]])), [[0, 0, 0, 1]])
    np.testing.assert_array_equal(quat_to_rot(np.array([[1.0, 0, 0, 0]])), np.eye(3)[None])


def _attitude_numpy(quat_wb, quat_sp, gain, limit, yaw_weight):
    """The reduced-attitude P loop as numpy expressions over (N, ...) arrays (the controller's formulation until
    2026-12-03): the reference its kernels must equal to the bit."""
    e_z, e_z_d = _quat_to_rot_numpy(quat_wb)[:, :, 2], _quat_to_rot_numpy(quat_sp)[:, :, 2]
    q_rot = np.concatenate((1.0 + np.sum(e_z * e_z_d, axis=1, keepdims=True), np.cross(e_z, e_z_d)), axis=1)
    n = np.linalg.norm(q_rot, axis=1, keepdims=True)
    q_red = _quat_mul_numpy(q_rot / np.maximum(n, 1e-12), quat_wb)
    q_red = np.where(n < 1e-6, quat_sp, q_red)
    q_mix = _quat_mul_numpy(quat_conj(q_red), quat_sp)
    q_mix = np.where(q_mix[:, :1] < 0.0, -q_mix, q_mix)
    half_w = yaw_weight * np.arccos(np.clip(q_mix[:, 0], -1.0, 1.0))
    half_z = yaw_weight * np.arcsin(np.clip(q_mix[:, 3], -1.0, 1.0))
    zero = np.zeros_like(half_w)
    q_d = _quat_mul_numpy(q_red, np.stack((np.cos(half_w), zero, zero, np.sin(half_z)), axis=1))
    q_e = _quat_mul_numpy(quat_conj(quat_wb), q_d)
    e = 2.0 * np.where(q_e[:, :1] < 0.0, -1.0, 1.0) * q_e[:, 1:]
    return np.clip(gain * e, -limit, limit)


def test_attitude_kernels_equal_the_numpy_attitude_loop_to_the_bit():
    """The attitude P loop (two numba kernels round numpy's arccos / arcsin / cos / sin) against its numpy
    formulation: random attitudes and setpoints, setpoints near the current one, antiparallel thrust axes (the full
    setpoint), rate-limited errors and per-vehicle gains; then hand values: no error gives zero rates, and a small
    roll error e gives K_p * 2 sin(e / 2) about x."""
    rng = np.random.default_rng(11)
    n = 300
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q_sp = rng.normal(size=(n, 4))
    q_sp /= np.linalg.norm(q_sp, axis=1, keepdims=True)
    q_sp[:100] = q[:100] + 0.05 * rng.normal(size=(100, 4))  # near the current attitude
    q_sp[:100] /= np.linalg.norm(q_sp[:100], axis=1, keepdims=True)
    q_sp[100:110] = _quat_mul_numpy(q[100:110], np.tile([0.0, 1.0, 0.0, 0.0], (10, 1)))  # flipped thrust axis
    cfg = VehicleConfig().controller
    ctrl = AttitudeRateController(n, cfg, 0.002)
    ctrl.attitude_p = ctrl.attitude_p * rng.uniform(0.5, 1.5, size=(n, 3))
    ref = _attitude_numpy(q, q_sp, ctrl.attitude_p, ctrl.rate_limit, ctrl.yaw_weight)
    assert (np.abs(ref) == ctrl.rate_limit).any()  # some rates are clipped
    np.testing.assert_array_equal(ctrl.attitude(q, q_sp), ref)
    np.testing.assert_array_equal(ctrl.attitude(q[:, ::-1][:, ::-1], q_sp), ref)  # a strided view
    one = AttitudeRateController(2, cfg, 0.002)
    level = np.array([[1.0, 0.0, 0.0, 0.0]] * 2)
    np.testing.assert_array_equal(one.attitude(level, level), np.zeros((2, 3)))
    err = 0.01
    rolled = np.array([[math.cos(err / 2), math.sin(err / 2), 0.0, 0.0]] * 2)
    expect = one.attitude_p[0, 0] * 2.0 * math.sin(err / 2)
    np.testing.assert_allclose(one.attitude(level, rolled)[:, 0], expect, rtol=1e-9)
    np.testing.assert_allclose(one.attitude(level, rolled)[:, 1:], 0.0, atol=1e-15)


def test_euler_zyx_round_trip_and_convention():
    # Positive pitch (FLU body, ZYX) tilts the thrust axis towards +x: R e3 = (sin th, 0, cos th).
    r = euler_zyx_to_rot(np.array([0.0]), np.array([0.3]), np.array([0.0]))[0]
    np.testing.assert_allclose(r[:, 2], [math.sin(0.3), 0.0, math.cos(0.3)], atol=1e-15)
    # Positive roll tilts it towards -y (right): R e3 = (0, -sin phi, cos phi).
    r = euler_zyx_to_rot(np.array([0.3]), np.array([0.0]), np.array([0.0]))[0]
    np.testing.assert_allclose(r[:, 2], [0.0, -math.sin(0.3), math.cos(0.3)], atol=1e-15)
    rng = np.random.default_rng(1)
    e = np.stack((rng.uniform(-1.2, 1.2, 40), rng.uniform(-1.2, 1.2, 40), rng.uniform(-3, 3, 40)), axis=1)
    np.testing.assert_allclose(rot_to_euler_zyx(euler_zyx_to_rot(*e.T)), e, atol=1e-12)


# ----------------------------------------------------------------------------- allocation
def test_effectiveness_hand_computed():
    # Arm 0.125 m -> each rotor at (+-a, +-a) with a = 0.125 / sqrt(2) = 0.0883883.
    b = effectiveness(0.125, 0.016)
    a = 0.125 / math.sqrt(2)
    np.testing.assert_allclose(b[0], [1, 1, 1, 1])
    np.testing.assert_allclose(b[1], [-a, a, a, -a])  # roll: y_i  (motor 1 front-right has y = -a)
    np.testing.assert_allclose(b[2], [-a, a, -a, a])  # pitch: -x_i
    np.testing.assert_allclose(b[3], [-0.016, -0.016, 0.016, 0.016])  # yaw: CCW rotors push -z


def test_allocator_scaling_and_hover():
    cfg = VehicleConfig()
    alloc = Allocator(cfg)
    t_max = cfg.max_motor_thrust  # 3.8 * 1 kg * 9.81 / 4 = 9.31950 N
    assert t_max == pytest.approx(9.3195)
    # Hover: every motor at m g / (4 T_max) = 1 / 3.8.
    u, sp, sn = alloc.allocate(np.array([G]), np.zeros((1, 3)))
    np.testing.assert_allclose(u, np.full((1, 4), 1 / 3.8), atol=1e-12)
    assert not sp.any() and not sn.any()
    # PX4 normalisation: roll torque 1 moves each motor by 1/sqrt(2); the physical scale is 2 T_max L.
    np.testing.assert_allclose(np.abs(alloc.mix[:, 1]), 1 / math.sqrt(2), atol=1e-12)
    assert alloc.torque_scale[0] == pytest.approx(2 * t_max * 0.125)
    assert alloc.torque_scale[2] == pytest.approx(4 * t_max * 0.016)


def test_allocator_unsaturated_is_exact_and_saturated_prioritises_roll_pitch():
    cfg = VehicleConfig()
    alloc = Allocator(cfg)
    torque = np.array([[0.05, -0.03, 0.02]])
    u, sp, sn = alloc.allocate(np.array([G]), torque)
    achieved = u @ alloc.effectiveness_n.T  # [F [N], roll, pitch, yaw]
    np.testing.assert_allclose(achieved[0, 1:], torque[0], atol=1e-12)
    assert achieved[0, 0] == pytest.approx(G)
    # Full thrust + roll + yaw: roll is kept, thrust lowered, yaw gets what is left (here nothing).
    u, sp, sn = alloc.allocate(np.array([4 * cfg.max_motor_thrust]), np.array([[0.5, 0.0, 0.8]]))
    assert np.all(u <= 1.0 + 1e-12) and np.all(u >= cfg.motor.min_thrust_fraction - 1e-12)
    achieved = u @ alloc.effectiveness_n.T
    assert achieved[0, 1] == pytest.approx(0.5, abs=1e-9)
    assert sp[0, 2] and not sp[0, 0]  # yaw flagged as saturated (anti-windup), roll not


# ----------------------------------------------------------------------------- closed loop
def test_hover_holds_altitude_after_a_rate_kick():
    # A 0.5 rad/s kick about x and y; the loop must level the vehicle and hold altitude within a few cm.
    out = hover_hold(duration=5.0, kick_rate=0.5)
    assert out["max_altitude_error_m"] < 0.04
    assert out["final_tilt_deg"] < 0.1
    assert out["xy_drift_m"] < 0.05


def test_roll_step_20deg_px4_like():
    # Expected: the attitude loop is first order with K_p = 6.5 /s (time constant 0.154 s, 10-90 % rise 0.34 s),
    # the rate loop adds a little lag that steepens the middle of the curve: measured rise 0.27 s, no overshoot.
    r = attitude_step("roll", 20.0, duration=1.5)
    assert 0.20 <= r.rise_time <= 0.35
    assert r.overshoot_pct < 5.0
    assert r.settling_time < 0.7
    assert abs(r.final - 20.0) < 0.3
    assert r.max_cross_axis < 0.5


def test_pitch_step_matches_roll_symmetry():
    r = attitude_step("pitch", -20.0, duration=1.0)
    assert 0.20 <= r.rise_time <= 0.35
    assert r.overshoot_pct < 5.0
    assert r.max_cross_axis < 0.5


def test_yaw_step_does_not_disturb_roll_pitch():
    # Yaw: K_p = 2.8 /s -> time constant 0.36 s, 10-90 % rise ~0.8 s; roll/pitch must stay level.
    r = attitude_step("yaw", 45.0, duration=2.5)
    assert 0.5 <= r.rise_time <= 1.0
    assert abs(r.final - 45.0) < 1.0
    assert r.max_cross_axis < 0.5


def test_level_flight_tilt_gives_g_tan_tilt_minus_drag():
    out = tilt_acceleration(15.0, duration=2.0)
    a = out["accel_measured"]
    # Forward acceleration equals the model prediction g tan(15 deg) - drag(v) within 2 %, and drag is real:
    # it takes a visible share of g tan(tilt) = 2.63 m/s^2 at the reached speed.
    assert a[0] == pytest.approx(out["accel_predicted"][0], rel=0.02)
    assert a[0] < 0.8 * out["accel_no_drag"]
    assert out["speed_m_s"] > 3.0
    assert abs(a[1]) < 1e-6


def test_saturation_keeps_attitude_authority_and_no_nan():
    # Allow collective commands up to 37 m/s^2 (99 % of the 37.28 m/s^2 the motors give) to force saturation.
    cfg = load_config(VehicleConfig, overrides=["controller.thrust_range=[1.0,37.0]"])
    veh = Vehicles(2, cfg)
    # Vehicle 0: maximal collective thrust and a 40 deg roll step. Vehicle 1: minimum thrust and the same step.
    lo, hi = cfg.controller.thrust_range
    cmd = np.array([[hi, math.radians(40), 0, 0], [lo, math.radians(40), 0, 0]])
    saturated = False
    roll = []
    for _ in range(60):
        veh.step(cmd)
        saturated |= bool(np.any(veh.motor_cmd_buf[0] >= 1.0 - 1e-9))
        roll.append(np.degrees(rot_to_euler_zyx(veh.R_wb)[:, 0]))
        assert np.all(np.isfinite(veh.data.qpos)) and np.all(np.isfinite(veh.data.qvel))
    roll = np.array(roll)
    assert saturated  # the motors did hit their ceiling
    assert roll[-1, 0] == pytest.approx(40.0, abs=1.5)  # and roll still tracked (thrust gave way, not attitude)
    assert roll[-1, 1] > 30.0  # at minimum thrust, roll authority is reduced but not lost


def test_out_of_range_commands_are_clamped():
    cfg = VehicleConfig()
    cmd = np.array([[100.0, 0.0, 0.0, 0.0], [-5.0, 0.0, 0.0, 0.0], [G, math.radians(80), 0.0, 0.3], [G, 0.7, 0.7, 0.0]])
    f_n, q_sp = attitude_setpoint(cmd, cfg.controller)
    np.testing.assert_allclose(f_n, [30.0, 1.0, G, G])
    tilt = np.degrees(np.arccos(quat_to_rot(q_sp)[:, 2, 2]))
    np.testing.assert_allclose(tilt[2:], cfg.controller.max_tilt_deg, atol=1e-9)
    # Roll and pitch of 0.7 rad (40 deg) each are within the limit, but together tilt the thrust axis by
    # acos(cos 0.7 cos 0.7) = 54.4 deg > 50 deg: the tilt is limited, keeping yaw and the tilt's direction.
    assert rot_to_euler_zyx(quat_to_rot(q_sp))[2, 2] == pytest.approx(0.3, abs=1e-9)
    z = quat_to_rot(q_sp)[3, :, 2]
    z_cmd = euler_zyx_to_rot(np.array([0.7]), np.array([0.7]), np.array([0.0]))[0, :, 2]
    np.testing.assert_allclose(z[:2] / np.linalg.norm(z[:2]), z_cmd[:2] / np.linalg.norm(z_cmd[:2]), atol=1e-12)
    # In flight: an 80 deg roll command ends at the 50 deg limit.
    veh = Vehicles(1, cfg)
    for _ in range(100):
        veh.step(cmd[2:3])
    assert np.degrees(math.acos(veh.R_wb[0, 2, 2])) == pytest.approx(cfg.controller.max_tilt_deg, abs=1.0)


def test_unconstrained_setpoint_is_the_euler_attitude():
    cfg = VehicleConfig()
    rng = np.random.default_rng(3)
    e = np.stack((rng.uniform(-0.5, 0.5, 20), rng.uniform(-0.5, 0.5, 20), rng.uniform(-3, 3, 20)), axis=1)
    e = e[np.cos(e[:, 0]) * np.cos(e[:, 1]) > math.cos(math.radians(cfg.controller.max_tilt_deg))]
    cmd = np.concatenate((np.full((len(e), 1), G), e), axis=1)
    _, q_sp = attitude_setpoint(cmd, cfg.controller)
    np.testing.assert_allclose(quat_to_rot(q_sp), euler_zyx_to_rot(*e.T), atol=1e-12)


def test_nan_command_names_the_vehicle():
    veh = Vehicles(4)
    cmd = np.tile([G, 0.0, 0.0, 0.0], (4, 1))
    cmd[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"vehicle index\(es\) \[2\]"):
        veh.step(cmd)
    with pytest.raises(ValueError, match="shape"):
        veh.step(cmd[:3])


def test_batching_is_exact():
    rng = np.random.default_rng(7)
    steps = 80
    cmds = np.empty((steps, 64, 4))
    cmds[..., 0] = rng.uniform(6, 16, (steps, 64))
    cmds[..., 1:3] = rng.uniform(-0.5, 0.5, (steps, 64, 2))
    cmds[..., 3] = rng.uniform(-1, 1, (steps, 64))
    one, many = Vehicles(1), Vehicles(64)
    start = np.array([[0.0, 0.0, 1.0]])
    one.reset(np.array([0]), start)
    many.reset(np.array([0]), start)
    for k in range(steps):
        one.step(cmds[k, :1])
        many.step(cmds[k])
        # Equal up to floating-point summation order in numpy's SIMD kernels (observed: 1 ulp).
        np.testing.assert_allclose(one.data.qpos[:7], many.data.qpos[:7], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(one.data.qvel[:6], many.data.qvel[:6], rtol=1e-12, atol=1e-13)


def test_reset_only_touches_given_vehicles_and_collision_with_obstacle():
    wall = '<geom type="box" pos="3 0 1" size="0.1 2 2" contype="1" conaffinity="2" group="1"/>'
    veh = Vehicles(2, world_xml=wall)
    veh.reset(np.array([0, 1]), np.array([[0.0, 0.0, 1.0], [0.0, 5.0, 1.0]]))
    fwd = np.array([[G / math.cos(0.4), 0.0, 0.4, 0.0]] * 2)
    hit_step = None
    for k in range(200):
        hit = veh.step(fwd)
        if hit[0] and hit_step is None:
            hit_step = k
        if hit_step is not None:
            break
    assert hit_step is not None and not veh.collided_buf[1]
    # Contact happens when the sphere (r = 0.2 m) reaches the wall face at x = 2.9 m.
    assert veh.pos_w[0, 0] == pytest.approx(2.9 - 0.2, abs=0.1)
    before = veh.pos_w[1].copy()
    veh.reset(np.array([0]), np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_array_equal(veh.pos_w[1], before)
    assert not veh.collided_buf[0]


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"controller\.rate_pp"):
        load_config(VehicleConfig, overrides=["controller.rate_pp=[1,1,1]"])
    with pytest.raises(ConfigError, match=r"airframe\.mass"):
        load_config(VehicleConfig, overrides=["airframe.mass=-1"])
    with pytest.raises(ConfigError, match=r"controller\.thrust_range"):
        load_config(VehicleConfig, overrides=["controller.thrust_range=[1,50]"])
    with pytest.raises(ConfigError, match=r"substeps"):
        load_config(VehicleConfig, overrides=["substeps=abc"])
