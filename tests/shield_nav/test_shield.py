"""The HOCBF shield: math against hand-computed values, QP properties, and scripted flights on the real simulator."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.camera import CameraConfig, DepthCamera, voxel_keys
from envs.config import ConfigError, load_config
from envs.scenes.primitives import Box
from shield_nav.safety.memory import _map_merge
from shield_nav.safety.shield import (
    STATUS_FALLBACK,
    STATUS_RELAXED,
    STATUS_SOLVED,
    HOCBFShield,
    ShieldConfig,
    accel_from_command,
    backup_distance,
    backup_rows,
    braking_rows,
    ceiling_row,
    command_from_accel,
    ground_row,
    hocbf_rows,
    passing_rows,
)
from shield_nav.tools.scripted import fly

G = 9.81
P4 = {"barrier": "distance", "alpha0": 16.0, "alpha1": 8.0, "lag_s": 0.0, "r_safe": 0.5}
"""The distance barrier at p1 = p2 = 4 /s without the lag (an earlier default), kept by the tests computed for it
(at the earlier default r_safe 0.5 m)."""
DIST = {"barrier": "distance", "r_safe": 0.5}
"""The paper's |r|^2 barrier at the default gains (p1 = p2 = 8 /s) and r_safe 0.5 m: the tests of that barrier,
computed at that radius, name it."""


def test_hocbf_row_hand_computed():
    # Vehicle at the origin moving +x at 3 m/s, obstacle point 2 m ahead. r = p - o = (-2, 0, 0).
    # B = 4 - 0.25 = 3.75;  Bdot = 2 r.v = -12;  A = 2 r = (-4, 0, 0);
    # b = -2|v|^2 - a1 Bdot - a0 B = -18 + 48 - 15 = 15.  So -4 a_x >= 15: brake at >= 3.75 m/s^2.
    a_mat, b_vec = hocbf_rows(np.array([[-2.0, 0.0, 0.0]]), np.array([3.0, 0.0, 0.0]), 4.0, 4.0, 0.5)
    np.testing.assert_allclose(a_mat, [[-4.0, 0.0, 0.0]])
    np.testing.assert_allclose(b_vec, [15.0])


def test_sign_convention_matches_the_time_derivatives():
    # The paper's Bdot = 2 r.v and Bddot = 2|v|^2 + 2 r.a hold for r = p - o (obstacle -> vehicle).
    # Check against finite differences of B(t) = |p(t) - o|^2 - r_safe^2 along p(t) = p0 + v0 t + a t^2 / 2.
    p0, v0, acc, o, rs = (
        np.array([0.3, -1.0, 1.2]),
        np.array([4.0, 1.0, -0.5]),
        np.array([-2.0, 3.0, 0.7]),
        np.array([5.0, 0.5, 1.0]),
        0.5,
    )

    def b_of(t: float) -> float:
        p = p0 + v0 * t + 0.5 * acc * t * t
        return float(np.sum((p - o) ** 2) - rs**2)

    h = 1e-4
    b_dot_fd = (b_of(h) - b_of(-h)) / (2 * h)
    b_ddot_fd = (b_of(h) - 2 * b_of(0.0) + b_of(-h)) / h**2
    r = p0 - o
    assert b_dot_fd == pytest.approx(2 * r @ v0, rel=1e-6)
    assert b_ddot_fd == pytest.approx(2 * v0 @ v0 + 2 * r @ acc, rel=1e-5)
    # With the paper's wording (r = o - p) the first derivative would have the opposite sign.
    assert b_dot_fd == pytest.approx(-2 * (o - p0) @ v0, rel=1e-6)
    # And the shield's rows are exactly HOCBF(B) >= 0 evaluated with r = p - o.
    a_mat, b_vec = hocbf_rows(r[None], v0, 3.0, 2.0, rs)
    lhs = b_ddot_fd + 2.0 * b_dot_fd + 3.0 * b_of(0.0)
    assert a_mat[0] @ acc - b_vec[0] == pytest.approx(lhs, rel=1e-5)


def test_accel_command_round_trip_is_identity():
    rng = np.random.default_rng(0)
    cmd = np.stack(
        (rng.uniform(5, 25, 50), rng.uniform(-0.6, 0.6, 50), rng.uniform(-0.6, 0.6, 50), rng.uniform(-3, 3, 50)), 1
    )
    a = accel_from_command(cmd)
    # Hover is a = 0; a level 0.3 rad pitch at f_n = g / cos(0.3) is a = (g tan 0.3, 0, 0).
    np.testing.assert_allclose(accel_from_command(np.array([[G, 0, 0, 1.0]])), [[0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(
        accel_from_command(np.array([[G / math.cos(0.3), 0, 0.3, 0]])), [[G * math.tan(0.3), 0, 0]], atol=1e-12
    )
    np.testing.assert_allclose(command_from_accel(a, cmd[:, 3]), cmd, atol=1e-10)
    # The shield's per-vehicle scalar kernel computes the same a_raw as the batched function.
    out = HOCBFShield().filter(cmd, np.zeros((50, 3)), np.zeros((50, 3)), points_w=[np.zeros((0, 3))] * 50)
    np.testing.assert_allclose(out.accel_raw, a, atol=1e-12)


def test_single_active_constraint_is_the_closed_form_half_space_projection():
    shield = HOCBFShield()
    a_raw = np.array([3.0, 0.5, 0.0])
    a_mat, b_vec = hocbf_rows(np.array([[-2.0, 0.0, 0.0]]), np.array([3.0, 0.0, 0.0]), 4.0, 4.0, 0.5)
    a_star, status, slack, _ = shield.solve(a_raw, a_mat, b_vec, np.zeros(3))
    # Projection onto {A a >= b}: a* = a_raw + (b - A a_raw) / |A|^2 A^T  ->  a_x = -3.75, a_y, a_z unchanged.
    expected = a_raw + (b_vec[0] - a_mat[0] @ a_raw) / (a_mat[0] @ a_mat[0]) * a_mat[0]
    np.testing.assert_allclose(expected, [-3.75, 0.5, 0.0])
    assert status == STATUS_SOLVED and slack == 0.0
    np.testing.assert_allclose(a_star, expected, atol=1e-9)


def test_correction_metric_steers_instead_of_braking_by_hand():
    # One row A a >= b with A = 2 r, r = p - o = (-2, -1, 0) (the point 2 m ahead, 1 m to the left), b = 8, at
    # a_raw = 0 and v = 9 m/s along x. Minimum-norm (W = I): a* = b A^T / |A|^2 = 8 (-4, -2, 0) / 20 = (-1.6, -0.8, 0).
    # W = diag(4, 1, 1) (along_weight 4): a* = b W^-1 A^T / (A W^-1 A^T) = 8 (-1, -2, 0) / (4 + 4) = (-1, -2, 0):
    # less braking, more steering away, and the row holds with equality either way.
    a_mat, b_vec = np.array([[-4.0, -2.0, 0.0]]), np.array([8.0])
    v = np.array([9.0, 0.0, 0.0])
    plain, status, *_ = HOCBFShield().solve(np.zeros(3), a_mat, b_vec, v)
    assert status == STATUS_SOLVED
    np.testing.assert_allclose(plain, [-1.6, -0.8, 0.0], atol=1e-9)
    steer, status, *_ = HOCBFShield(ShieldConfig(along_weight=4.0)).solve(np.zeros(3), a_mat, b_vec, v)
    assert status == STATUS_SOLVED
    np.testing.assert_allclose(steer, [-1.0, -2.0, 0.0], atol=1e-9)
    # The weight follows the horizontal velocity: flying along y, the same row's braking axis is y. W = diag(1, 4, 1):
    # W^-1 A^T = (-4, -0.5, 0), A W^-1 A^T = 17, a* = 8 / 17 (-4, -0.5, 0).
    along_y, *_ = HOCBFShield(ShieldConfig(along_weight=4.0)).solve(np.zeros(3), a_mat, b_vec, np.array([0, 9.0, 0]))
    np.testing.assert_allclose(along_y, np.array([-4.0, -0.5, 0.0]) * 8 / 17, atol=1e-9)
    # vertical_weight: a point above-ahead, r = (-2, 0, -1), b = 8, at v = 0 (no along-weight), W = diag(1, 1, 4):
    # W^-1 A^T = (-4, 0, -0.5), A W^-1 A^T = 17, a* = 8 / 17 (-4, 0, -0.5) (identity: 8 / 20 (-4, 0, -2)).
    a_up = np.array([[-4.0, 0.0, -2.0]])
    low, *_ = HOCBFShield(ShieldConfig(vertical_weight=4.0)).solve(np.zeros(3), a_up, b_vec, np.zeros(3))
    np.testing.assert_allclose(low, np.array([-4.0, 0.0, -0.5]) * 8 / 17, atol=1e-9)
    with pytest.raises(ValueError, match="along_weight"):
        HOCBFShield(ShieldConfig(along_weight=0.0))


def test_safe_command_is_returned_bit_exact():
    shield = HOCBFShield()
    cmd = np.array([[G / math.cos(0.2), 0.05, 0.2, 0.3]])
    # One point 8 m ahead, vehicle at 2 m/s: every HOCBF row is satisfied with a wide margin.
    pos, vel = np.array([[0.0, 0.0, 1.5]]), np.array([[2.0, 0.0, 0.0]])
    out = shield.filter(cmd, pos, vel, points_w=[np.array([[8.0, 0, 1.5]])])
    assert not out.active[0] and out.status[0] == 0 and out.num_constraints[0] == 1
    assert np.array_equal(out.command, cmd)


def test_unsafe_command_is_corrected_to_satisfy_every_selected_row():
    shield = HOCBFShield()
    cmd = np.array([[G / math.cos(0.3), 0.0, 0.3, 0.0]])  # accelerating towards a wall 2 m ahead at 6 m/s
    ys, zs = np.meshgrid(np.linspace(-2, 2, 41), np.linspace(0, 3, 31))
    wall = np.stack((np.full(ys.size, 2.0), ys.ravel(), zs.ravel()), 1)
    pos, vel = np.array([[0.0, 0.0, 1.5]]), np.array([[6.0, 0.0, 0.0]])
    out = shield.filter(cmd, pos, vel, points_w=[wall])
    assert out.active[0] and out.status[0] in (STATUS_SOLVED, STATUS_RELAXED)
    _, a_mat, b_vec = shield.constraints(wall, pos[0], vel[0], out.accel_raw[0])
    if out.status[0] == STATUS_SOLVED:
        assert np.all(a_mat @ out.accel_safe[0] >= b_vec - 1e-6)
    assert out.accel_safe[0, 0] < 0.0  # it brakes
    # The corrected command is what the vehicle flies: accel_from_command(command) reproduces a*.
    np.testing.assert_allclose(accel_from_command(out.command), out.accel_safe, atol=1e-9)


@settings(max_examples=150, deadline=None)
@given(
    st.integers(1, 8),
    st.integers(0, 2**31 - 1),
)
def test_property_feasible_solutions_satisfy_all_constraints(k, seed):
    rng = np.random.default_rng(seed)
    shield = HOCBFShield()
    r = rng.normal(size=(k, 3)) * rng.uniform(0.3, 4.0)
    v = rng.normal(size=3) * 4.0
    a_raw = rng.normal(size=3) * 5.0
    a_mat, b_vec = hocbf_rows(r, v, 4.0, 4.0, 0.5)
    a_star, status, slack, _ = shield.solve(a_raw, a_mat, b_vec, v)
    assert np.all(np.isfinite(a_star))
    # Always flyable: inside the actuator polytope.
    assert np.all(shield._g_act @ a_star <= shield._h_act + 1e-6)
    if status == STATUS_SOLVED:
        assert np.all(a_mat @ a_star >= b_vec - 1e-6 * (1 + np.abs(b_vec)))
        # Optimality against a projection that ignores the obstacle rows: never closer than a_raw's projection.
    else:
        assert status == STATUS_RELAXED and slack > 0.0
        assert np.all(a_mat @ a_star + slack >= b_vec - 1e-4 * (1 + np.abs(b_vec)))


def test_infeasible_instance_returns_relaxed_solution_with_slack():
    shield = HOCBFShield()
    # Hovering between two points 0.3 m either side (inside r_safe = 0.5): B = 0.09 - 0.25 = -0.16, Bdot = 0, so
    # each row asks 0.6 a_x >= 0.64 and -0.6 a_x >= 0.64: a_x >= 1.067 and a_x <= -1.067 -- infeasible.
    r = np.array([[0.3, 0.0, 0.0], [-0.3, 0.0, 0.0]])
    a_mat, b_vec = hocbf_rows(r, np.zeros(3), 4.0, 4.0, 0.5)
    np.testing.assert_allclose(b_vec, [0.64, 0.64])
    a_star, status, slack, _ = shield.solve(np.zeros(3), a_mat, b_vec, np.zeros(3))
    assert status == STATUS_RELAXED
    # By symmetry a_x = 0 and both rows need the same slack 0.64 (up to the 1e4 penalty's tiny give).
    assert a_star[0] == pytest.approx(0.0, abs=1e-6)
    assert slack == pytest.approx(0.64, rel=1e-3)
    assert np.all(shield._g_act @ a_star <= shield._h_act + 1e-6)


@pytest.mark.parametrize("solver", ["osqp", "quadprog"])
def test_other_backends_agree_with_daqp(solver):
    rng = np.random.default_rng(5)
    fast, other = HOCBFShield(), HOCBFShield(ShieldConfig(solver=solver))
    for _ in range(10):
        r = rng.normal(size=(6, 3)) * 2.0
        v, a_raw = rng.normal(size=3) * 3.0, rng.normal(size=3) * 4.0
        a_mat, b_vec = hocbf_rows(r, v, 4.0, 4.0, 0.5)
        x1, s1, *_ = fast.solve(a_raw, a_mat, b_vec, v)
        x2, s2, *_ = other.solve(a_raw, a_mat, b_vec, v)
        assert s1 == s2
        np.testing.assert_allclose(x1, x2, atol=1e-4 if solver == "osqp" else 1e-7)


def test_depth_input_selects_points_on_the_wall():
    cam = CameraConfig()
    wall = Box((5.1, 0.0, 1.5), (0.1, 4.0, 1.5))
    depth = DepthCamera(cam, [[wall]]).render(np.array([[0.0, 0.0, 1.5]]), np.eye(3)[None])
    shield = HOCBFShield(camera=cam)
    out = shield.filter(np.array([[G, 0, 0, 0]]), np.array([[0.0, 0.0, 1.5]]), np.array([[3.0, 0, 0]]), depth=depth,
                        R_wb=np.eye(3)[None])  # fmt: skip
    from envs.camera import depth_to_points

    pts = depth_to_points(depth[0], np.array([0.0, 0.0, 1.5]), np.eye(3), cam)
    r, _, _ = shield.constraints(pts, np.array([0.0, 0.0, 1.5]), np.array([3.0, 0, 0]), np.zeros(3))
    assert out.num_constraints[0] == len(r) >= 1
    np.testing.assert_allclose(-r[:, 0], 5.0, atol=1e-6)  # every selected point lies on the face x = 5


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="solver"):
        load_config(ShieldConfig, overrides=["solver=nope"])
    with pytest.raises(ConfigError, match="alpha0"):
        load_config(ShieldConfig, overrides=["alpha0=-1"])
    with pytest.raises(ConfigError, match="min_altitude"):
        load_config(ShieldConfig, overrides=["min_altitude=-0.1"])
    with pytest.raises(ValueError, match=r"index\(es\) \[1\]"):
        HOCBFShield().filter(np.array([[G, 0, 0, 0], [np.nan, 0, 0, 0]]), np.zeros((2, 3)), np.zeros((2, 3)),
                             points_w=[np.zeros((0, 3))] * 2)  # fmt: skip


@pytest.mark.parametrize("kind", ["pole", "wall"])
def test_scripted_flights_shield_prevents_collisions(kind):
    speeds = [3.0, 5.0, 7.0, 9.0]
    bare = fly(kind, speeds, shielded=False, duration=4.5)
    assert bare.collided.all()  # the naive controller crashes at every speed
    # Measured minimum 3-D distances over 4.5 s from the vehicle centre to the surface, pole / wall (braking barrier,
    # a_b 10, lag 0.15 s, 2026-11-26), at 3 / 5 / 7 / 9 m/s: r_safe 0.5 m: pole 0.51 / 0.50 / 0.50 / 0.50, wall
    # 0.51 / 0.50 / 0.50 / 0.50; the default r_safe 0.3 m: pole 0.31 / 0.30 / 0.30 / 0.28, wall 0.31 / 0.30 / 0.30 /
    # 0.28 (a_b 8: 0.31 / 0.30 / 0.30 / 0.30 for both). The controller keeps pushing, so the
    # distance creeps towards r_safe; assert r_safe minus 0.1 m (the point cloud's pixel sampling and what the
    # one-lag prediction leaves of the lag), and no contact (collision radius 0.2 m).
    for r_safe in (0.5, ShieldConfig().r_safe):
        safe = fly(kind, speeds, shielded=True, duration=4.5, shield_cfg=ShieldConfig(r_safe=r_safe))
        assert not safe.collided.any()
        assert np.all(safe.min_distance > r_safe - 0.1)
        assert safe.active.any(axis=0).all()


def test_selected_rows_equal_hocbf_rows_and_one_per_sector():
    shield = HOCBFShield(ShieldConfig(**DIST, max_constraints=4, azimuth_sectors=4, elevation_sectors=1))
    pos, vel = np.array([0.0, 0.0, 1.0]), np.array([2.0, -1.0, 0.0])
    # Sectors of 90 deg in azimuth starting at -180 deg: [-180, -90), [-90, 0), [0, 90), [90, 180].
    # Three points ahead-left (azimuth 0..3 deg, one sector), one to the right (-90 deg), one behind (180 deg).
    pts = np.array([[3.0, 0.1, 1.0], [2.5, 0.0, 1.0], [4.0, 0.2, 1.0], [0.0, -2.0, 1.0], [-3.0, 0.0, 1.0]])
    r, a_mat, b_vec = shield.constraints(pts, pos, vel, np.zeros(3))
    a_ref, b_ref = hocbf_rows(r, vel, shield.cfg.alpha0, shield.cfg.alpha1, 0.5)
    np.testing.assert_allclose(a_mat, a_ref)
    np.testing.assert_allclose(b_vec, b_ref)
    # Of the three points ahead only the tightest (the nearest, 2.5 m) is kept.
    assert len(r) == 3
    assert any(np.allclose(row, pos - pts[1]) for row in r)
    assert not any(np.allclose(row, pos - pts[0]) or np.allclose(row, pos - pts[2]) for row in r)


def test_ground_points_are_filtered_and_would_otherwise_trigger_level_flight():
    # Level flight at 5 m/s, 1.5 m above a floor sampled every 0.25 m. For a floor point x metres ahead, at zero
    # acceleration the HOCBF row reads 2|v|^2 + a1 (2 r.v) + a0 (|r|^2 - r_safe^2) = 4x^2 - 40x + 58 (a0 = a1 = 4),
    # negative for 1.76 m < x < 8.24 m: the unfiltered shield brakes and climbs although nothing is in the way.
    # (With the default p1 = p2 = 8 the same row, 64x^2 - 160x + 178, has no real root: larger gains trigger later.)
    xs, ys = np.meshgrid(np.arange(0.0, 10.0, 0.25), np.arange(-3.0, 3.0, 0.25))
    floor = np.stack((xs.ravel(), ys.ravel(), np.zeros(xs.size)), 1)
    cmd = np.array([[G, 0.0, 0.0, 0.0]])
    pos, vel = np.array([[0.0, 0.0, 1.5]]), np.array([[5.0, 0.0, 0.0]])
    gains = {"barrier": "distance", "alpha0": 4.0, "alpha1": 4.0, "lag_s": 0.0, "r_safe": 0.5}
    on = HOCBFShield(ShieldConfig(**gains)).filter(cmd, pos, vel, points_w=[floor])
    off = HOCBFShield(ShieldConfig(**gains, z_window=[-1.0e9, 1.0e9])).filter(cmd, pos, vel, points_w=[floor])
    assert not on.active[0] and on.num_constraints[0] == 0
    assert off.active[0] and off.accel_safe[0, 2] > 0.0  # the unfiltered floor pushes the vehicle up


def test_point_memory_keeps_constraints_for_obstacles_that_left_the_view():
    # Step 1 sees a pole point 1.5 m ahead-left; step 2 sees nothing (the pole left the field of view) while the
    # vehicle still drifts towards it. Only the shield with memory keeps the constraint (and its row is the same
    # obstacle point, now relative to the new position). At step 2: r = p - o = (-0.3, -0.4, 0), B = 0,
    # Bdot = 2 r.v = -1.1, Bddot(a_raw) = 2|v|^2 + 2 r.a_raw = 2.5 - 0.8 g tan(0.3) = 0.07, so the row value
    # 0.07 + 4 * (-1.1) + 0 < 0: violated.
    pole = np.array([[1.5, 0.8, 1.5]])
    cmd = np.array([[G / math.cos(0.3), -0.3, 0.0, 0.0]])  # rolling left, towards +y
    vel = np.array([[0.5, 1.0, 0.0]])
    plain = HOCBFShield(ShieldConfig(memory_steps=0, map_seconds=0.0))  # the paper: the current image only
    mem = HOCBFShield(ShieldConfig(memory_steps=10, map_seconds=0.0))  # the sparse memory alone
    for sh in (plain, mem):
        first = sh.filter(cmd, np.array([[0.0, 0.0, 1.5]]), vel, points_w=[pole])
        assert first.num_constraints[0] == 1
    pos2 = np.array([[1.2, 0.4, 1.5]])
    out_plain = plain.filter(cmd, pos2, vel, points_w=[np.zeros((0, 3))])
    out_mem = mem.filter(cmd, pos2, vel, points_w=[np.zeros((0, 3))])
    assert out_plain.num_constraints[0] == 0 and not out_plain.active[0]
    assert out_mem.num_constraints[0] == 1 and out_mem.active[0]
    r, _, _ = mem.constraints(pole, pos2[0], vel[0], out_mem.accel_raw[0])
    np.testing.assert_allclose(r, pos2 - pole)
    mem.reset([0])
    assert mem.filter(cmd, pos2, vel, points_w=[np.zeros((0, 3))]).num_constraints[0] == 0


def test_point_memory_from_depth_matches_the_same_points_given_as_a_list():
    from envs.camera import depth_to_points

    # The depth path appends the remembered points in place after the image's; the point-list path concatenates.
    # Fed the same clouds (the images' own back-projections) over a flight past a box, both filter alike.
    cam = CameraConfig()
    camera = DepthCamera(cam, [[Box((3.0, -0.8, 1.5), (0.3, 0.3, 1.5))]])
    by_depth, by_list = HOCBFShield(ShieldConfig(), cam), HOCBFShield(ShieldConfig(), cam)
    cmd = np.array([[G / math.cos(0.2), 0.2, -0.3, 0.0]])  # rolling right, towards the box
    remembered, active = 0, 0
    for k in range(35):
        pos, vel, r_wb = np.array([[0.1 * k, -0.012 * k, 1.5]]), np.array([[3.0, -0.36, 0.0]]), np.eye(3)[None]
        depth = camera.render(pos, r_wb)
        a = by_depth.filter(cmd, pos, vel, depth=depth, R_wb=r_wb)
        pts = depth_to_points(depth[0], pos[0], r_wb[0], cam)
        b = by_list.filter(cmd, pos, vel, points_w=[pts])
        np.testing.assert_array_equal(a.command, b.command)
        assert a.num_constraints[0] == b.num_constraints[0]
        remembered = max(remembered, int(np.sum(~np.isnan(by_depth._memory[0][:, 0]))))
        active += int(a.active[0])
    assert remembered > 0 and active > 0


def test_local_map_keeps_a_seen_obstacle_the_sparse_memory_dropped():
    # Call 1 sees two points: a far wall point straight ahead (tightest) and a pole point 1.5 m ahead-left. With
    # max_constraints 1 the sparse memory keeps only the selected point; call 2 sees nothing while the vehicle drifts
    # to the pole (the geometry of the point-memory test above: its row there is violated). Only the local map
    # still holds the pole, so only the shield with the map keeps the constraint, at the pole's own point.
    pole, wall = np.array([1.5, 0.8, 1.5]), np.array([0.9, 0.0, 1.5])
    cmd = np.array([[G / math.cos(0.3), -0.3, 0.0, 0.0]])
    vel = np.array([[0.5, 1.0, 0.0]])
    sparse = HOCBFShield(ShieldConfig(memory_steps=10, max_constraints=1, map_seconds=0.0))
    mapped = HOCBFShield(ShieldConfig(memory_steps=10, max_constraints=1, map_seconds=1.0, map_voxel=0.2))
    for sh in (sparse, mapped):
        sh.filter(cmd, np.array([[0.0, 0.0, 1.5]]), vel, points_w=[np.stack((pole, wall))])
    np.testing.assert_allclose(sparse._memory[0][0], wall)  # the one point the sparse memory kept
    pos2 = np.array([[1.2, 0.4, 1.5]])
    nothing = [np.zeros((0, 3))]
    out_sparse = sparse.filter(cmd, pos2, vel, points_w=nothing)
    out_map = mapped.filter(cmd, pos2, vel, points_w=nothing)
    np.testing.assert_allclose(np.sort(mapped.map_points(0), axis=0), np.sort(np.stack((pole, wall)), axis=0))
    assert out_map.active[0] and not out_sparse.active[0]  # the wall (behind-right now) does not bind; the pole does
    r, _, _ = mapped.constraints(pole[None], pos2[0], vel[0], out_map.accel_raw[0])
    np.testing.assert_allclose(r, pos2 - pole)
    mapped.reset([0])
    assert len(mapped.map_points(0)) == 0


def test_local_map_thins_to_the_newest_point_per_cube_and_forgets_by_age_and_distance():
    # map_every 1 (every call takes in its image), 0.5 m cubes, 0.05 s (5 calls) of age, 3 m of radius.
    cfg = ShieldConfig(memory_steps=0, map_seconds=0.05, map_voxel=0.5, map_radius=3.0, map_every=1)
    sh = HOCBFShield(cfg)
    cmd, vel, far = np.array([[G, 0.0, 0.0, 0.0]]), np.zeros((1, 3)), np.array([[-20.0, 0.0, 1.5]])
    at = np.array([[0.0, 0.0, 1.5]])
    a, b, beyond = [2.10, 0.10, 1.60], [2.40, 0.45, 1.90], [3.5, 0.0, 1.5]  # a and b share the cube (4, 0, 3)
    floor = [1.0, 0.0, 0.05]  # below the z window's 0.15 m: never taken in
    sh.filter(cmd, at, vel, points_w=[np.array([a, beyond, floor])])
    np.testing.assert_allclose(sh.map_points(0), [a])  # beyond (3.5 m) and the floor are not taken in
    sh.filter(cmd, at, vel, points_w=[np.array([b])])
    np.testing.assert_allclose(sh.map_points(0), [b])  # same cube: the newer point replaces the older
    for _ in range(4):  # calls 2-5: nothing seen; b (stamp 1) is 1-4 calls old, kept
        sh.filter(cmd, at, vel, points_w=[np.zeros((0, 3))])
    np.testing.assert_allclose(sh.map_points(0), [b])
    sh.filter(cmd, at, vel, points_w=[np.zeros((0, 3))])  # call 6: 5 calls old, still within 0.05 s
    assert len(sh.map_points(0)) == 1
    sh.filter(cmd, at, vel, points_w=[np.zeros((0, 3))])  # call 7: 6 calls old: forgotten
    assert len(sh.map_points(0)) == 0
    sh.filter(cmd, at, vel, points_w=[np.array([a])])
    sh.filter(cmd, far, vel, points_w=[np.zeros((0, 3))])  # the vehicle is now 22 m away: a is dropped
    assert len(sh.map_points(0)) == 0
    # map_every 3: only calls 0, 3, 6, ... take in their image.
    every3 = HOCBFShield(ShieldConfig(memory_steps=0, map_seconds=1.0, map_every=3))
    for k in range(4):
        every3.filter(cmd, at, vel, points_w=[np.array([[1.0 + k, 0.0, 1.5]])])
    np.testing.assert_allclose(np.sort(every3.map_points(0)[:, 0]), [1.0, 4.0])


def _map_merge_numpy(img, old, old_st, p, r2, z_lo, z_hi, calls, max_age, voxel):
    """The local map's intake as numpy writes it (the implementation before ``_map_merge``): the reference."""
    new = img[(((img - p) ** 2).sum(axis=1) <= r2) & (img[:, 2] >= z_lo) & (img[:, 2] <= z_hi)]
    keep = (calls - old_st <= max_age) & (((old - p) ** 2).sum(axis=1) <= r2)
    new, stamps = np.concatenate((new, old[keep])), np.concatenate((np.full(len(new), calls), old_st[keep]))
    _, first = np.unique(voxel_keys(new, voxel), return_index=True)
    return new[first], stamps[first]


def test_map_merge_by_hand():
    # 0.5 m cubes, radius 3 m, 4 calls of age at call 10. Image: a and b share the cube (4, 0, 3) (a is first, so
    # it is kept), c is beyond 3 m, d is below the z window. Old map: e shares a's cube (the image's point wins), f
    # is 5 calls old (dropped), g is kept; the output is in cube-key order: (2, 1, 2) for g before (4, 0, 3) for a.
    a, b, c, d = [2.10, 0.10, 1.60], [2.40, 0.45, 1.90], [3.5, 0.0, 1.5], [1.0, 0.0, 0.05]
    e, f, g = [2.2, 0.2, 1.7], [0.6, 0.6, 1.2], [1.1, 0.7, 1.2]
    pts, st = _map_merge(np.array([a, b, c, d]), np.array([e, f, g]), np.array([7, 5, 6]),
                         np.array([0.0, 0.0, 1.5]), 9.0, 0.15, 10.0, 10, 4, 0.5)  # fmt: skip
    np.testing.assert_array_equal(pts, [g, a])
    np.testing.assert_array_equal(st, [6, 10])
    empty, empty_st = _map_merge(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(3), 9.0, 0.15,
                                 10.0, 0, 4, 0.5)  # fmt: skip
    assert empty.shape == (0, 3) and empty_st.shape == (0,)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_img=st.integers(0, 400), n_old=st.integers(0, 300),
       voxel=st.sampled_from([0.1, 0.2, 0.5]))  # fmt: skip
def test_map_merge_equals_the_numpy_intake(seed, n_img, n_old, voxel):
    # Clouds on a coarse lattice (so many points share a cube and sit exactly on the radius and the z window's
    # edges) plus jitter: the same points, stamps and order as np.unique's first indices.
    rng = np.random.default_rng(seed)
    img = rng.integers(-16, 17, (n_img, 3)) * 0.25 + rng.choice([0.0, 1e-3], (n_img, 3))
    old = rng.integers(-16, 17, (n_old, 3)) * 0.25 + rng.choice([0.0, 1e-3], (n_old, 3))
    old_st = rng.integers(0, 30, n_old)
    args = (np.array([0.25, -0.5, 0.5]), 9.0, 0.25, 3.0, 30, 12, voxel)
    got, ref = _map_merge(img, old, old_st, *args), _map_merge_numpy(img, old, old_st, *args)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


def test_local_map_in_the_cloud_buffer_grows_and_matches_the_concatenation():
    # A map larger than the room left in the shield's cloud buffer: the buffer grows, keeps the image's points, and
    # the cloud equals the image's points followed by the map's.
    sh = HOCBFShield(ShieldConfig(memory_steps=0, map_every=1, map_voxel=0.1))
    sh._cloud = np.empty((10, 3))
    img = np.stack((np.linspace(1.0, 4.0, 30), np.zeros(30), np.full(30, 1.5)), axis=1)  # 30 cubes of 0.1 m
    sh._cloud[:4] = img[:4]
    cloud = sh._with_map(0, sh._cloud[:4], 4, np.zeros(3), True)  # the map takes in the 4 image points
    np.testing.assert_array_equal(cloud, np.concatenate((img[:4], img[:4])))
    big = sh._with_map(0, img, 30, np.zeros(3), False)  # not in the buffer: concatenated; the map is now 30 points
    np.testing.assert_array_equal(big, np.concatenate((img, img)))
    sh._cloud[:4] = img[:4]
    cloud = sh._with_map(0, sh._cloud[:4], 4, np.zeros(3), True)
    assert len(sh._cloud) >= 34
    np.testing.assert_array_equal(cloud, np.concatenate((img[:4], img)))


def test_local_map_config_errors_name_the_key():
    for key, val in (("map_seconds", -1.0), ("map_seconds", float("nan")), ("map_voxel", 0.0), ("map_radius", 0.0),
                     ("map_every", 0), ("map_every", 1.5)):  # fmt: skip
        with pytest.raises(ValueError, match=f"shield.{key}"):
            ShieldConfig(**{key: val}).validate("shield.")


def test_a_shield_stored_before_the_local_map_default_reads_back_without_it():
    # The map is on by default (2 s); a shield config written before the key existed flew without it, so
    # stored_config reads the missing key as 0 (PRE_FIELD_VALUES), and keeps a stored value as it is.
    from envs.config import stored_config

    assert ShieldConfig().map_seconds == 2.0
    assert stored_config(ShieldConfig, {"r_safe": 0.5})["map_seconds"] == 0.0
    assert stored_config(ShieldConfig, {"map_seconds": 1.5})["map_seconds"] == 1.5
    assert ShieldConfig(**stored_config(ShieldConfig, {"r_safe": 0.5})).map_seconds == 0.0


def test_ground_row_hand_computed_and_projection():
    # Descending at 2 m/s, 0.5 m high, min_altitude 0.35, alpha0 16, alpha1 8: b = -8 (-2) - 16 (0.15) = 13.6.
    assert ground_row(0.5, -2.0, 16.0, 8.0, 0.35) == pytest.approx(13.6)
    cmd = np.array([[G, 0.0, 0.0, 0.3]])  # a_raw = 0 (hover thrust, level), yaw 0.3
    pos, vel = np.array([[4.0, 1.0, 0.5]]), np.array([[3.0, 0.0, -2.0]])
    nothing = [np.zeros((0, 3))]
    off = HOCBFShield(ShieldConfig(**P4, min_altitude=0.0)).filter(cmd, pos, vel, points_w=nothing)
    assert not off.active[0] and np.array_equal(off.command, cmd)  # the paper's shield ignores the ground
    on = HOCBFShield(ShieldConfig(**P4, min_altitude=0.35)).filter(cmd, pos, vel, points_w=nothing)
    default = HOCBFShield(ShieldConfig(**P4)).filter(cmd, pos, vel, points_w=nothing)
    np.testing.assert_array_equal(default.command, on.command)  # the row is on by default, at 0.35 m
    # The only row is a_z >= 13.6; the projection of a_raw = 0 onto it is (0, 0, 13.6), within the thrust limits.
    assert on.active[0] and on.status[0] == STATUS_SOLVED and on.num_constraints[0] == 0
    np.testing.assert_allclose(on.accel_safe[0], [0.0, 0.0, 13.6], atol=1e-6)
    np.testing.assert_allclose(on.command[0], [G + 13.6, 0.0, 0.0, 0.3], atol=1e-6)
    # Level flight at 1.5 m: b = -16 (1.15) < 0 = a_z, inactive, the command is returned bit for bit.
    high, cruise = np.array([[4.0, 1.0, 1.5]]), np.array([[5.0, 0.0, 0.0]])
    level = HOCBFShield(ShieldConfig(**P4, min_altitude=0.35)).filter(cmd, high, cruise, points_w=nothing)
    assert not level.active[0] and np.array_equal(level.command, cmd)


def test_ground_row_joins_the_obstacle_rows():
    # A pole point ahead and slightly above forces a correction that dips the vehicle; near the ground the ground
    # row caps how far down: the solution satisfies both the obstacle rows and a_z >= b_ground.
    shield = HOCBFShield(ShieldConfig(**P4, min_altitude=0.35))
    pos, vel = np.array([[0.0, 0.0, 0.45]]), np.array([[5.0, 0.0, -1.0]])
    bar = np.array([[2.0, y, 0.9] for y in np.arange(-2.0, 2.01, 0.1)])  # a horizontal bar 2 m ahead, 0.45 m up
    cmd = np.array([[G, 0.0, 0.0, 0.0]])
    out = shield.filter(cmd, pos, vel, points_w=[bar])
    r, a_mat, b_vec = shield.constraints(bar, pos[0], vel[0], np.zeros(3))
    b_g = ground_row(0.45, -1.0, 16.0, 8.0, 0.35)
    assert out.active[0] and len(b_vec) > 0
    assert out.accel_safe[0, 2] >= b_g - 1e-6
    assert np.all(a_mat @ out.accel_safe[0] >= b_vec - 1e-6)
    plain = HOCBFShield(ShieldConfig(**P4, min_altitude=0.0)).filter(cmd, pos, vel, points_w=[bar])
    assert plain.accel_safe[0, 2] < b_g  # without the row the correction goes down, into the ground


def test_ceiling_row_hand_computed_and_projection():
    # Climbing at 1 m/s, 2.7 m high, max_altitude 3.0, alpha0 16, alpha1 8: b = 8 (1) - 16 (0.3) = 3.2, i.e.
    # the row -a_z >= 3.2 caps the vertical acceleration at a_z <= -3.2.
    assert ceiling_row(2.7, 1.0, 16.0, 8.0, 3.0) == pytest.approx(3.2)
    cmd = np.array([[G, 0.0, 0.0, 0.3]])  # a_raw = 0 (hover thrust, level), yaw 0.3
    pos, vel = np.array([[4.0, 1.0, 2.7]]), np.array([[3.0, 0.0, 1.0]])
    nothing = [np.zeros((0, 3))]
    off = HOCBFShield(ShieldConfig(**P4)).filter(cmd, pos, vel, points_w=nothing)
    assert not off.active[0] and np.array_equal(off.command, cmd)
    on = HOCBFShield(ShieldConfig(**P4, max_altitude=3.0)).filter(cmd, pos, vel, points_w=nothing)
    # The projection of a_raw = 0 onto a_z <= -3.2 is (0, 0, -3.2): thrust G - 3.2, level attitude.
    assert on.active[0] and on.status[0] == STATUS_SOLVED and on.num_constraints[0] == 0
    np.testing.assert_allclose(on.accel_safe[0], [0.0, 0.0, -3.2], atol=1e-6)
    np.testing.assert_allclose(on.command[0], [G - 3.2, 0.0, 0.0, 0.3], atol=1e-6)
    # Level flight at 1.5 m: b = -16 (1.5) = -24 <= 0 = -a_z, inactive, the command is returned bit for bit.
    level = HOCBFShield(ShieldConfig(**P4, max_altitude=3.0)).filter(
        cmd, np.array([[4.0, 1.0, 1.5]]), np.array([[5.0, 0.0, 0.0]]), points_w=nothing
    )
    assert not level.active[0] and np.array_equal(level.command, cmd)


def test_ceiling_row_keeps_the_obstacle_correction_below_the_geofence():
    # A bar 2 m ahead, 0.45 m below a vehicle climbing at 1 m/s: the obstacle rows alone lift it over the bar
    # (a_z > 0); with the ceiling at 3.0 m (b = 8 (1) - 16 (0.45) = 0.8) the solution keeps a_z <= -0.8 and still
    # satisfies every obstacle row (it brakes instead).
    pos, vel = np.array([[0.0, 0.0, 2.55]]), np.array([[5.0, 0.0, 1.0]])
    bar = np.array([[2.0, y, 2.1] for y in np.arange(-2.0, 2.01, 0.1)])
    cmd = np.array([[G, 0.0, 0.0, 0.0]])
    plain = HOCBFShield(ShieldConfig(**P4)).filter(cmd, pos, vel, points_w=[bar])
    assert plain.active[0] and plain.accel_safe[0, 2] > 0.0
    shield = HOCBFShield(ShieldConfig(**P4, max_altitude=3.0))
    out = shield.filter(cmd, pos, vel, points_w=[bar])
    _, a_mat, b_vec = shield.constraints(bar, pos[0], vel[0], np.zeros(3))
    assert out.active[0] and out.status[0] == STATUS_SOLVED and len(b_vec) > 0
    assert out.accel_safe[0, 2] <= -0.8 + 1e-6
    assert np.all(a_mat @ out.accel_safe[0] >= b_vec - 1e-6)
    assert out.accel_safe[0, 0] < plain.accel_safe[0, 0]  # harder braking replaces the climb


def test_altitude_rows_stay_hard_when_the_obstacle_rows_are_relaxed():
    # One obstacle row -a_x + a_z >= 40 that the tilt and thrust limits cannot meet: the relaxed QP buys it back
    # with all the thrust it has, half of it upward (a_z > 0). Given the ceiling row -a_z >= 2 it keeps a_z = -2
    # exactly (hard, not traded against the slack) and pays with a larger slack.
    shield = HOCBFShield(ShieldConfig(**P4))
    a_mat, b_vec = np.array([[-1.0, 0.0, 1.0]]), np.array([40.0])
    free, status, slack_free, _ = shield.solve(np.zeros(3), a_mat, b_vec, np.zeros(3))
    assert status == STATUS_RELAXED and free[2] > 5.0
    capped, status, slack_capped, _ = shield.solve(
        np.zeros(3), a_mat, b_vec, np.zeros(3), np.array([[0.0, 0.0, -1.0]]), np.array([2.0])
    )
    assert status == STATUS_RELAXED and capped[2] == pytest.approx(-2.0, abs=1e-6)
    assert slack_capped > slack_free


def test_altitude_rows_are_capped_at_what_the_actuators_can_give():
    # Climbing at 3 m/s, 0.1 m under the ceiling: b = 8 (3) - 16 (0.1) = 22.4, i.e. a_z <= -22.4, beyond the
    # -8.81 m/s^2 that the minimum thrust (1 m/s^2) gives. The row is capped to a_z <= -8.81 + 0.001 and the QP
    # solves exactly: level attitude, thrust 1.001.
    shield = HOCBFShield(ShieldConfig(**P4, max_altitude=3.0))
    out = shield.filter(np.array([[G, 0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 2.9]]), np.array([[3.0, 0.0, 3.0]]),
                        points_w=[np.zeros((0, 3))])  # fmt: skip
    assert out.status[0] == STATUS_SOLVED
    np.testing.assert_allclose(out.accel_safe[0], [0.0, 0.0, 1.0 - G + 1e-3], atol=1e-6)
    np.testing.assert_allclose(out.command[0, :3], [1.001, 0.0, 0.0], atol=1e-6)
    # Descending at 6 m/s, 0.1 m above the ground row: b = 8 (6) - 16 (0.1) = 46.4 > what 30 m/s^2 of thrust
    # gives; the row asks for the most the level thrust cap allows, which the QP gives.
    low = HOCBFShield(ShieldConfig(**P4, min_altitude=0.35))
    out = low.filter(np.array([[G, 0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 0.45]]), np.array([[0.0, 0.0, -6.0]]),
                     points_w=[np.zeros((0, 3))])  # fmt: skip
    assert out.status[0] == STATUS_SOLVED
    assert out.accel_safe[0, 2] == pytest.approx(30.0 * low.thrust_cap_scale - G - 1e-3, abs=1e-6)


def test_altitude_band_config_is_checked():
    with pytest.raises(ConfigError, match="max_altitude"):
        load_config(ShieldConfig, overrides=["min_altitude=0.5", "max_altitude=0.4"])
    with pytest.raises(ConfigError, match="max_altitude"):
        load_config(ShieldConfig, overrides=["max_altitude=-1"])
    assert load_config(ShieldConfig, overrides=["min_altitude=0.35", "max_altitude=3.0"]).max_altitude == 3.0


def _all_margins(pts, p, v, a, cfg):
    """Row margins A a - b of every point the shield considers (point_filter distances, z_window heights), computed
    independently of the shield's selection: for the distance barrier 2 r.a + 2|v|^2 + alpha1 (2 r.v) + alpha0
    (|r|^2 - r_safe^2), for the braking barrier from ``braking_rows``."""
    r = p - pts
    d = np.linalg.norm(r, axis=1)
    keep = (d >= cfg.point_filter[0]) & (d <= cfg.point_filter[1]) & (pts[:, 2] >= cfg.z_window[0])
    r = r[keep]
    if cfg.barrier == "braking":
        a_mat, b_vec = braking_rows(r, v, cfg.r_safe, cfg.brake_accel, cfg.brake_gain)
        return a_mat @ a - b_vec
    return 2 * r @ a + 2 * v @ v + cfg.alpha1 * 2 * r @ v + cfg.alpha0 * (np.sum(r * r, axis=1) - cfg.r_safe**2)


def _random_clouds(n, seed):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        p = np.array([0.0, 0.0, 1.5])
        # A dense cloud ahead: a pole or wall patch plus scattered points, 0.6-6 m away.
        pts = p + rng.uniform([0.6, -3.0, -1.0], [6.0, 3.0, 1.0], size=(int(rng.integers(50, 400)), 3))
        v = np.array([rng.uniform(2.0, 9.0), rng.normal() * 1.5, rng.normal() * 0.3])
        cmd = np.array([[9.81 + rng.normal() * 2, rng.normal() * 0.2, rng.uniform(-0.5, 0.1), 0.0]])
        yield p, v, pts, cmd


def test_active_set_answer_keeps_every_cloud_point_safe():
    """Against every point of random clouds, not only the selected ones: the corrected acceleration satisfies all
    rows whenever the hard QP was solved. With the paper's one-shot selection (active_set_iterations 0) some
    answers break the row of a point that was not selected (the defect the iteration removes)."""
    fixed, paper = HOCBFShield(ShieldConfig(**P4)), HOCBFShield(ShieldConfig(**P4, active_set_iterations=0))
    solved = broken_paper = 0
    for p, v, pts, cmd in _random_clouds(300, 11):
        out = fixed.filter(cmd, p[None], v[None], points_w=[pts])
        if out.active[0] and out.status[0] == STATUS_SOLVED:
            solved += 1
            m = _all_margins(pts, p, v, out.accel_safe[0], fixed.cfg)
            assert m.min() >= -fixed.cfg.active_set_tol - 1e-5 * (1 + np.abs(m).max())
        ref = paper.filter(cmd, p[None], v[None], points_w=[pts])
        if ref.active[0] and ref.status[0] == STATUS_SOLVED:
            broken_paper += _all_margins(pts, p, v, ref.accel_safe[0], paper.cfg).min() < -0.01
    assert solved >= 100
    assert broken_paper >= 5
    # The default shield (braking barrier, lag 0.15 s) and the distance barrier at p = 8 with the lag: a solved
    # answer keeps every point's row at the current state too (a point competes with the tighter of its two rows,
    # in the selection and in the check at a*).
    for cfg, min_solved in ((ShieldConfig(), 50), (ShieldConfig(**DIST), 50)):
        shield, solved = HOCBFShield(cfg), 0
        for p, v, pts, cmd in _random_clouds(300, 11):
            shield.reset()  # each cloud is a new vehicle (no velocity history: zero acceleration in the prediction)
            out = shield.filter(cmd, p[None], v[None], points_w=[pts])
            if out.active[0] and out.status[0] == STATUS_SOLVED:
                solved += 1
                m = _all_margins(pts, p, v, out.accel_safe[0], cfg)
                assert m.min() >= -cfg.active_set_tol - 1e-5 * (1 + np.abs(m).max())
        assert solved >= min_solved, cfg.barrier


def test_active_set_iterations_zero_is_the_one_shot_selection():
    """The switch: with 0 iterations the shield solves exactly the K rows selected at the raw command."""
    shield = HOCBFShield(ShieldConfig(active_set_iterations=0))
    for p, v, pts, cmd in _random_clouds(40, 5):
        out = shield.filter(cmd, p[None], v[None], points_w=[pts])
        assert out.num_constraints[0] <= shield.cfg.max_constraints


def test_lag_rows_are_the_barrier_at_the_predicted_state():
    """With lag_s the shield measures the acceleration from the velocity one control_dt ago and, per point, keeps
    the tighter of its row now and its row at the state one lag ahead. Hand-computed: head-on at 5 m/s towards a
    point 3 m ahead, braking at 2 m/s^2 (velocity 5.02 -> 5.00 over 10 ms), lag 0.15 s:
    p_lag = 0.75 - 0.0225 = 0.7275 m further, v_lag = 5 - 0.3 = 4.7 m/s; r_lag = (-2.2725, 0, 0).
    B = 5.16425625 - 0.25 = 4.91425625, Bdot = 2 r.v = -21.3615, b = -2 (22.09) - 8 Bdot - 16 B = 48.0839."""
    shield = HOCBFShield(ShieldConfig(**DIST, alpha0=16.0, alpha1=8.0, lag_s=0.15, control_dt=0.01))
    p, o = np.array([0.0, 0.0, 1.5]), np.array([[3.0, 0.0, 1.5]])  # above the shield's ground filter
    cmd = command_from_accel(np.zeros((1, 3)), np.zeros(1))
    shield.filter(cmd, p[None], np.array([[5.02, 0.0, 0.0]]), points_w=[o])  # the velocity of the previous call
    v_prev = shield._prev_vel[0].copy()
    out = shield.filter(cmd, p[None], np.array([[5.0, 0.0, 0.0]]), points_w=[o])
    np.testing.assert_allclose(v_prev, [5.02, 0, 0])
    # Independently: the row the shield solved against is hocbf_rows at (p_lag, v_lag), so the answer is the
    # projection of a_raw = 0 onto -4.545 a_x >= 48.0839 (one active row, inside the actuator limits).
    a_mat, b_vec = hocbf_rows(np.array([[-2.2725, 0.0, 0.0]]), np.array([4.7, 0.0, 0.0]), 16.0, 8.0, 0.5)
    assert b_vec[0] == pytest.approx(48.0839, abs=1e-3)
    assert out.active[0] and out.status[0] == STATUS_SOLVED
    np.testing.assert_allclose(out.accel_safe[0], [b_vec[0] / a_mat[0, 0], 0.0, 0.0], atol=1e-6)
    # Without the lag the same state needs less braking: the row at (p, v) alone.
    a0, b0 = hocbf_rows(p - o, np.array([5.0, 0.0, 0.0]), 16.0, 8.0, 0.5)
    plain = HOCBFShield(ShieldConfig(**DIST, alpha0=16.0, alpha1=8.0, lag_s=0.0)).filter(
        cmd, p[None], np.array([[5.0, 0.0, 0.0]]), points_w=[o]
    )
    np.testing.assert_allclose(plain.accel_safe[0], [b0[0] / a0[0, 0], 0.0, 0.0], atol=1e-6)
    assert out.accel_safe[0, 0] < plain.accel_safe[0, 0] < 0
    # reset forgets the velocity: the next call predicts with zero acceleration.
    shield.reset([0])
    assert 0 not in shield._prev_vel


def test_lag_prediction_that_passes_a_point_keeps_the_current_row():
    """A prediction that has passed a point ((p_lag - o).(p - o) <= 0) would give a row pushing towards it; that
    point keeps its row at the current state instead. 0.2 m before a point at 1.5 m/s, lag 0.15 s, p1 = p2 = 6:
    the predicted state is 0.025 m beyond it, where the row reads 0.05 a_x >= 3.5775 (a_x >= 72 m/s^2, forward
    through the point). The current row, -0.4 a_x >= 10.26, brakes; the answer is the lag-free shield's."""
    gains = {"barrier": "distance", "alpha0": 36.0, "alpha1": 12.0, "r_safe": 0.5}
    p, o, v = np.array([0.0, 0.0, 1.5]), np.array([[0.2, 0.0, 1.5]]), np.array([[1.5, 0.0, 0.0]])
    a_lag, b_lag = hocbf_rows(np.array([[0.025, 0.0, 0.0]]), v[0], 36.0, 12.0, 0.5)
    assert a_lag[0, 0] == pytest.approx(0.05) and b_lag[0] == pytest.approx(3.5775)
    cmd = command_from_accel(np.zeros((1, 3)), np.zeros(1))
    out = HOCBFShield(ShieldConfig(**gains, lag_s=0.15)).filter(cmd, p[None], v, points_w=[o])
    ref = HOCBFShield(ShieldConfig(**gains, lag_s=0.0)).filter(cmd, p[None], v, points_w=[o])
    assert out.active[0] and out.accel_safe[0, 0] < 0
    np.testing.assert_allclose(out.accel_safe[0], ref.accel_safe[0], atol=1e-9)


@pytest.mark.parametrize("kind", ["pole", "wall"])
def test_lag_aware_shield_stays_clear_where_the_lag_free_one_hits(kind):
    """The delay-aware barrier on the full vehicle (attitude loop and motors in the loop). With the gains raised to
    p1 = p2 = 8 /s (later, harder corrections) the lag-free shield lets the vehicle hit the obstacle at 5 m/s
    (measured minimum distance 0.19 m to the pole's and the wall's surface, contact); with lag_s = 0.15 s the same
    gains stop it at 0.50 m. Both flights start 12 m away at 5 m/s."""
    gains = {"barrier": "distance", "alpha0": 64.0, "alpha1": 16.0, "r_safe": 0.5, "map_seconds": 0.0}
    lag_free = fly(kind, [5.0], shielded=True, duration=4.5, shield_cfg=ShieldConfig(**gains, lag_s=0.0))
    lagged = fly(kind, [5.0], shielded=True, duration=4.5, shield_cfg=ShieldConfig(**gains, lag_s=0.15))
    assert lag_free.collided.all()
    assert not lagged.collided.any() and lagged.min_distance[0] > 0.4


def test_step_response_lag_is_what_the_shield_models():
    """The lag the delay-aware barrier uses (0.15 s in the shield configs) against the vehicle's step response,
    measured on the full simulator: 63 % of a 5 m/s^2 step after 0.16 s, equivalent first-order delay 0.141 s
    (docs/shield.md, "Lag"). A change of the attitude loop or the motor model that moves these shows here."""
    from shield_nav.tools.scripted import step_response

    r = step_response()
    assert r["final_accel"] == pytest.approx(5.0, abs=0.05)
    assert r["t10_s"] < r["t50_s"] < r["t63_s"] < r["t90_s"]
    assert r["t63_s"] == pytest.approx(0.16, abs=0.011)
    assert r["equivalent_delay_s"] == pytest.approx(0.141, abs=0.01)


@pytest.mark.parametrize(("kind", "speed"), [("pole", 7.0), ("pole", 9.0), ("wall", 7.0), ("wall", 9.0)])
def test_point_mass_flights_stay_outside_r_safe_where_the_one_shot_selection_does_not(kind, speed):
    """The shield's own filter in the loop of a point mass (no lag: the geometry alone), every visible surface point
    given. Measured minimum distances (r_safe 0.5 m), one-shot selection (the paper's, p = 4) -> default shield:
    pole 7 m/s 0.418 -> 0.775, pole 9 m/s 0.418 -> 0.500, wall at 30 deg 7 m/s 0.488 -> 0.744, 9 m/s 0.488 ->
    0.522. The one-shot selection ranks each sector's points at the raw command; the point that binds after the
    correction is dropped and the vehicle is let inside r_safe. The p = 4 active set alone gives 0.500 / 0.500 at
    the pole and 0.525 / 0.524 at the wall: it is the selection, not the gains."""
    from shield_nav.tools.scripted import point_mass_flight

    one_shot = point_mass_flight(kind, speed, ShieldConfig(**P4, active_set_iterations=0))
    active_set = point_mass_flight(kind, speed, ShieldConfig(**P4))
    default = point_mass_flight(kind, speed, ShieldConfig(**DIST))
    tol = 0.005  # the discrete 10 ms steps
    assert default >= 0.5 - tol and active_set >= 0.5 - tol
    assert one_shot < 0.5 - tol


def test_braking_row_hand_computed():
    # Head-on: vehicle at the origin at 7 m/s towards a point 3 m ahead; r = p - o = (-3, 0, 0), d = 3, n = (-1, 0, 0),
    # closing speed c = 7, s = sqrt(2 * 6 * (3 - 0.5)) = sqrt(30) = 5.477226, h = s - c = -1.522774.
    # b = -4 h + 6 c / s - (|v|^2 - c^2) / d = 6.091097 + 7.668116 - 0 = 13.759213: n.a >= 13.76, i.e. brake at
    # 13.76 m/s^2 (more than a_b: h < 0, the point is already inside the braking distance). Scaled by 2d = 6.
    a_mat, b_vec = braking_rows(np.array([[-3.0, 0.0, 0.0]]), np.array([7.0, 0.0, 0.0]), 0.5, 6.0, 4.0)
    np.testing.assert_allclose(a_mat, [[-6.0, 0.0, 0.0]])
    np.testing.assert_allclose(b_vec, [6.0 * 13.759213], rtol=1e-6)
    # Passing sideways: point 2 m to the side, v = 5 m/s tangential, c = 0, s = sqrt(18) = 4.242641:
    # b = -4 s - 25 / 2 = -29.470563, scaled by 2d = 4.
    a_mat, b_vec = braking_rows(np.array([[-2.0, 0.0, 0.0]]), np.array([0.0, 5.0, 0.0]), 0.5, 6.0, 4.0)
    np.testing.assert_allclose(b_vec, [4.0 * -29.470563], rtol=1e-6)


def test_braking_row_is_the_first_order_cbf_of_its_barrier():
    # h(t) = sqrt(2 a_b (|r| - r_safe)) - c along p(t) = p0 + v0 t + acc t^2 / 2 (c = -r.v / |r|); the row's value
    # n.acc - b must equal hdot + gain h, with hdot from finite differences.
    p0, v0, acc, o = np.array([0.3, -1.0, 1.2]), np.array([4.0, 1.0, -0.5]), np.array([-2.0, 3.0, 0.7]), \
        np.array([5.0, 0.5, 1.0])  # fmt: skip
    rs, a_b, gain = 0.5, 6.0, 3.0
    h0, h_dot = _barrier_and_rate(
        lambda r, v: math.sqrt(2 * a_b * (np.linalg.norm(r) - rs)) + r @ v / np.linalg.norm(r), p0, v0, acc, o
    )
    r = p0 - o
    a_mat, b_vec = braking_rows(r[None], v0, rs, a_b, gain)
    d = np.linalg.norm(r)
    assert (a_mat[0] @ acc - b_vec[0]) / (2 * d) == pytest.approx(h_dot + gain * h0, rel=1e-6)


def _barrier_and_rate(h, p0, v0, acc, o, eps=1e-5):
    """``h(r, v)`` at t = 0 along p(t) = p0 + v0 t + acc t^2 / 2 (r = p - o), and its rate by central differences."""

    def h_of(t: float) -> float:
        return h(p0 + v0 * t + 0.5 * acc * t * t - o, v0 + acc * t)

    return h_of(0.0), (h_of(eps) - h_of(-eps)) / (2 * eps)


def test_braking_barrier_stops_a_head_on_approach_with_at_most_its_deceleration():
    """A point mass at 9 m/s flies at a point 12 m ahead with no command of its own (a_raw = 0) and only the shield
    acting, no lag. The point becomes a row 10 m away (the point filter), where the braking barrier (a_b = 6 m/s^2
    here) is inside its safe set (h = sqrt(2 * 6 * 9.5) - 9 = 1.68 m/s), so it brakes at no more than a_b and stops
    outside r_safe. The distance barrier at its default gains (p1 = p2 = 8 /s) leaves the braking late and then asks
    for more than the tilt limit gives (g tan 50 = 11.7)."""
    o = np.array([[12.0, 0.0, 1.5]])
    cmd = np.array([[G, 0.0, 0.0, 0.0]])  # hover thrust, level: a_raw = 0
    results = {}
    for barrier in ("braking", "distance"):
        shield = HOCBFShield(ShieldConfig(barrier=barrier, brake_accel=6.0, lag_s=0.0, r_safe=0.5))
        pos, vel = np.array([0.0, 0.0, 1.5]), np.array([9.0, 0.0, 0.0])
        peak_demand, d_min = 0.0, math.inf
        for _ in range(2000):  # 4 s in 2 ms steps (the barrier's discrete-time overshoot shrinks with the step)
            _, a_mat, b_vec = shield.constraints(o, pos, vel, np.zeros(3))
            if len(b_vec):  # the point is a row once within the 10 m point filter
                # The row's demand along n = (-1, 0, 0): -a_x >= b / |A|.
                peak_demand = max(peak_demand, float(b_vec[0] / np.linalg.norm(a_mat[0])))
            out = shield.filter(cmd, pos[None], vel[None], points_w=[o])
            vel = vel + 0.002 * out.accel_safe[0]
            pos = pos + 0.002 * vel
            d_min = min(d_min, float(np.linalg.norm(pos - o[0])))
        results[barrier] = (peak_demand, d_min)
    demand, d_min = results["braking"]
    assert demand <= 6.0 + 0.05 and d_min >= 0.5 - 0.005
    assert results["distance"][0] > G * math.tan(math.radians(50.0))


def test_barrier_config_is_checked():
    with pytest.raises(ConfigError, match="barrier"):
        ShieldConfig(barrier="cone").validate()
    with pytest.raises(ConfigError, match="brake_accel"):
        ShieldConfig(barrier="braking", brake_accel=0.0).validate()
    with pytest.raises(ConfigError, match="brake_gain"):
        ShieldConfig(brake_gain=float("nan")).validate()
    with pytest.raises(ConfigError, match="passing.*needs barrier 'braking'"):
        ShieldConfig(barrier="distance", passing=True).validate()
    with pytest.raises(ConfigError, match="passing"):
        ShieldConfig(passing="yes").validate()


def test_passing_row_hand_computed():
    # A point 1 m beside the path, 3 m ahead, at 9 m/s: r = p - o = (-3, 1, 0), v = (9, 0, 0), r_safe 0.3, a_b 8,
    # gain 4. d = sqrt(10) = 3.162278; braking: e = 2.862278, s = sqrt(16 e) = 6.767307, c = 27 / d = 8.538150,
    # h_b = s - c = -1.770843 < 0 (braking at 8 m/s^2 along n no longer stops the approach). Cone: S = sqrt(9.91)
    # = 3.148015, h_c = r.v + |v| S = -27 + 28.332137 = 1.332137 >= 0 (v points outside the 0.3 m ball's cone), so
    # the cone row: A = r + S v / |v| = (0.148015, 1, 0), b = -4 h_c - 81 - 9 (-27) / S = -5.328549 - 81 +
    # 77.191494 = -9.137055; a = 0 meets it. The braking row alone asks 2 r.a >= 2 d b = 92.435497, i.e. 15.4 m/s^2
    # of braking for a point straight flight passes 1 m away.
    r, v, a0 = np.array([[-3.0, 1.0, 0.0]]), np.array([9.0, 0.0, 0.0]), np.zeros(3)
    a_mat, b_vec, cone = passing_rows(r, v, a0, 0.3, 8.0, 4.0)
    assert cone.tolist() == [True]
    np.testing.assert_allclose(a_mat, [[0.148015, 1.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(b_vec, [-9.137055], atol=1e-6)
    np.testing.assert_allclose(braking_rows(r, v, 0.3, 8.0, 4.0)[1], [92.435497], atol=1e-6)
    # Head-on (inside the cone: h_c = -9 (3 - S') < 0): the braking row, unchanged.
    r = np.array([[-3.0, 0.0, 0.0]])
    a_mat, b_vec, cone = passing_rows(r, v, a0, 0.3, 8.0, 4.0)
    a_brake, b_brake = braking_rows(r, v, 0.3, 8.0, 4.0)
    assert cone.tolist() == [False]
    np.testing.assert_array_equal(a_mat, a_brake)
    np.testing.assert_array_equal(b_vec, b_brake)
    # Both hold (a point 6 m ahead, 1 m aside: d = sqrt(37) = 6.082763, h_b = sqrt(16 (d - 0.3)) - 54 / d = 0.741 > 0,
    # h_c = -54 + 9 sqrt(36.91) = 0.678 > 0): the row nearer to being met at a, by its value over |A|. At a = 0 the
    # braking row is broken (b = 49.366, value -49.366 / 2d = -4.058) and the cone row met (+3.707): cone. Turning
    # hard towards the point, a = (0, -10, 0), both break, the braking row less (-5.702 against -6.265): braking.
    r = np.array([[-6.0, 1.0, 0.0]])
    np.testing.assert_allclose(braking_rows(r, v, 0.3, 8.0, 4.0)[1], [49.366002], atol=1e-6)
    assert passing_rows(r, v, a0, 0.3, 8.0, 4.0)[2].tolist() == [True]
    assert passing_rows(r, v, np.array([0.0, -10.0, 0.0]), 0.3, 8.0, 4.0)[2].tolist() == [False]


def test_passing_row_is_the_first_order_cbf_of_the_cone_barrier():
    # h_c(t) = r.v + |v| sqrt(|r|^2 - r_safe^2) along p(t) = p0 + v0 t + acc t^2 / 2; the cone row's value A.acc - b
    # must equal hdot_c + gain h_c, with hdot_c from finite differences.
    # (The point is inside the braking distance, h_b < 0, and outside the collision cone, h_c = 0.818: the cone row.)
    p0, v0, acc, o = np.array([0.3, -1.0, 1.2]), np.array([6.0, 1.0, -0.5]), np.array([-2.0, 3.0, 0.7]), \
        np.array([1.8, 0.0, 1.0])  # fmt: skip
    rs, a_b, gain = 0.3, 8.0, 3.0
    h0, h_dot = _barrier_and_rate(lambda r, v: r @ v + np.linalg.norm(v) * math.sqrt(r @ r - rs * rs), p0, v0, acc, o)
    assert h0 > 0
    a_mat, b_vec, cone = passing_rows((p0 - o)[None], v0, np.zeros(3), rs, a_b, gain)
    assert cone[0]
    assert a_mat[0] @ acc - b_vec[0] == pytest.approx(h_dot + gain * h0, rel=1e-6)


@pytest.mark.parametrize("lag", [False, True])
def test_passing_kernel_rows_equal_the_reference(lag):
    """The numba selection's rows with ``passing`` are ``passing_rows`` of the selected points (at the raw command;
    with the lag, at the lagged state where that row is the tighter), and the cone rows do occur."""
    rng = np.random.default_rng(5)
    shield = HOCBFShield(ShieldConfig(passing=True, lag_s=0.0))
    cfg = shield.cfg
    cones = rows = 0
    for p, v, pts, cmd in _random_clouds(80, 13):
        a_raw = accel_from_command(cmd)[0]
        lagged = (p + 0.15 * v + rng.normal(0.0, 0.1, 3), v + rng.normal(0.0, 1.0, 3)) if lag else None
        _, a_mat, b_vec = shield.constraints(pts, p, v, a_raw, lagged)
        for o, a_row, b in zip(shield._o_buf[: len(b_vec)], a_mat, b_vec, strict=True):
            cands = [(p, v)] + ([lagged] if lag and (lagged[0] - o) @ (p - o) > 0 else [])
            ref = [passing_rows((ps - o)[None], vs, a_raw, cfg.r_safe, cfg.brake_accel, cfg.brake_gain)
                   for ps, vs in cands]  # fmt: skip
            # The point's tighter row at a_raw is the one selected.
            vals = [a_r[0] @ a_raw - b_r[0] for a_r, b_r, _ in ref]
            a_ref, b_ref, c_ref = ref[int(np.argmin(vals))] if len(vals) == 1 or vals[1] < vals[0] else ref[0]
            np.testing.assert_allclose(a_row, a_ref[0], rtol=1e-9, atol=1e-9)
            assert b == pytest.approx(b_ref[0], rel=1e-9, abs=1e-9)
            cones += int(c_ref[0])
            rows += 1
    assert rows > 300 and 0 < cones < rows


def _fly_past_poles(cfg: ShieldConfig, offset: float) -> tuple[float, float, int]:
    """A point mass at 9 m/s along +x with a_raw = 0 past a row of poles ``offset`` beside its path (points every
    3 m from x = 5 m, 0.5-2.5 m high), 3 s in 5 ms Euler steps behind ``cfg``'s shield: its lowest speed, its
    closest distance to a pole point, and the steps on which the shield acted."""
    xs, zs = np.arange(5.0, 45.0, 3.0), np.linspace(0.5, 2.5, 9)
    poles = np.array([[x, offset, z] for x in xs for z in zs])
    cmd = np.array([[G, 0.0, 0.0, 0.0]])
    shield = HOCBFShield(cfg)
    pos, vel = np.array([0.0, 0.0, 1.5]), np.array([9.0, 0.0, 0.0])
    v_min = d_min = math.inf
    active = 0
    for _ in range(600):
        out = shield.filter(cmd, pos[None], vel[None], points_w=[poles])
        active += int(out.active[0])
        vel = vel + 0.005 * out.accel_safe[0]
        pos = pos + 0.005 * vel
        v_min = min(v_min, float(np.linalg.norm(vel)))
        d_min = min(d_min, float(np.min(np.linalg.norm(poles - pos, axis=1))))
    return v_min, d_min, active


@pytest.mark.parametrize("offset", [1.0, 0.6, 0.0])
def test_passing_keeps_speed_beside_obstacles_and_still_stops_head_on(offset):
    """A point mass cruising at 9 m/s (a_raw = 0, no lag) along a row of poles (points every 3 m, 0.5-2.5 m high)
    ``offset`` beside its path. Straight flight passes each pole ``offset`` away, outside r_safe = 0.3 m: with
    ``passing`` the shield leaves it alone (speed 9 m/s, closest approach = offset), while the braking barrier alone
    brakes for every pole (measured with the default a_b 10: down to 7.2 / 6.0 m/s at offsets 1.0 / 0.6; with a_b 8,
    6.9 / 5.7) and pushes the vehicle aside. Head-on
    (offset 0) both stop outside r_safe."""
    result = {
        passing: _fly_past_poles(ShieldConfig(lag_s=0.0, memory_steps=0, passing=passing), offset)
        for passing in (False, True)
    }
    if offset > 0:
        v_min, d_min, active = result[True]
        assert active == 0 and v_min == 9.0 and d_min == pytest.approx(offset, abs=1e-4)  # sampled every 4.5 cm
        assert result[False][0] < 7.5 and result[False][2] > 0
    else:
        for v_min, d_min, _ in result.values():
            assert v_min < 1e-3 and d_min >= 0.3 - 0.005


def test_backup_rows_hand_computed():
    # 9 m/s along +x, a_b 10, gain 4, r_safe 0.3: the backup maneuver stops S = 81 / 20 = 4.05 m on.
    # (a) A point 3 m ahead, 1 m aside, r = p - o = (-3, 1, 0): x = 3 < S, so D = m = 1, h = 0.7; r_perp = (0, 1, 0);
    #     A = (x / S) r_perp = (0, 0.740741, 0), b = -(2 a_b / |v|) gain m (m - r_safe) = -(20 / 9) 4 0.7 = -6.222222:
    #     a = 0 meets it (the braking row asks 2 r.a >= 92.4 here at a_b 8, test_passing_row_hand_computed).
    # (b) 6 m ahead, 1 m aside: x - S = 1.95, D = sqrt(1.95^2 + 1) = 2.191461; A = -2 (x - S) u + r_perp =
    #     (-3.9, 1, 0), b = 2 a_b (x - S) - (20 / 9) 4 D (D - 0.3) = 39 - 36.844994 = 2.155006 (a = 0 breaks it; the
    #     row asks a_x <= -0.5526: mild braking while the stopping point still lies short of the point).
    # (c) 2 m behind, 1 m aside: no row (A = 0, b = -inf).
    # (d) 3 m ahead, 0.1 m aside: D = 0.1 < r_safe (the backup maneuver would pass too close): the braking row.
    r, v = np.array([[-3.0, 1.0, 0.0], [-6.0, 1.0, 0.0], [2.0, 1.0, 0.0], [-3.0, 0.1, 0.0]]), np.array([9.0, 0, 0])
    a_mat, b_vec, use = backup_rows(r, v, 0.3, 10.0, 4.0)
    assert use.tolist() == [True, True, True, False]
    np.testing.assert_allclose(backup_distance(r, v, 10.0), [1.0, 2.191461, math.sqrt(5.0), 0.1], atol=1e-6)
    np.testing.assert_allclose(a_mat[:3], [[0.0, 0.740741, 0.0], [-3.9, 1.0, 0.0], [0.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(b_vec[:2], [-6.222222, 2.155006], atol=1e-6)
    assert b_vec[2] == -np.inf
    a_brake, b_brake = braking_rows(r[3:], v, 0.3, 10.0, 4.0)
    np.testing.assert_array_equal(a_mat[3:], a_brake)
    np.testing.assert_array_equal(b_vec[3:], b_brake)
    # Head-on, 6 m ahead: A = -2 (x - S) u = 2 r-direction, the braking barrier's normal; braking at a_b along -v
    # meets the row with gain * D (D - r_safe) to spare.
    a_mat, b_vec, _ = backup_rows(np.array([[-6.0, 0.0, 0.0]]), v, 0.3, 10.0, 4.0)
    np.testing.assert_allclose(a_mat, [[-3.9, 0.0, 0.0]])
    assert a_mat[0] @ np.array([-10.0, 0, 0]) - b_vec[0] == pytest.approx(20.0 / 9.0 * 4.0 * 1.95 * 1.65)
    # Slower than PASSING_MIN_SPEED: braking rows only.
    assert not backup_rows(r, np.array([0.4, 0.0, 0.0]), 0.3, 10.0, 4.0)[2].any()


def test_backup_row_is_the_first_order_cbf_of_the_backup_distance():
    """On random states the row's value A.a - b equals (2 a_b D / |v|)(Ddot + gain h), h = D - r_safe, with Ddot from
    finite differences of ``backup_distance`` along p(t) = p0 + v0 t + a t^2 / 2; both sides of the stopping point
    occur."""
    rng = np.random.default_rng(3)
    a_b, gain, rs = 10.0, 4.0, 0.3
    seen = {"beside": 0, "ahead": 0}
    for _ in range(400):
        p0, v0, acc = rng.normal(0, 1, 3), rng.normal(0, 4, 3), rng.normal(0, 5, 3)
        o = p0 + rng.normal(0, 3, 3)
        a_mat, b_vec, use = backup_rows((p0 - o)[None], v0, rs, a_b, gain)
        if not use[0] or not np.isfinite(b_vec[0]):
            continue
        big_d, d_dot = _barrier_and_rate(lambda r, v: backup_distance(r[None], v, a_b)[0], p0, v0, acc, o, eps=1e-6)
        speed = np.linalg.norm(v0)
        expect = 2.0 * a_b * big_d / speed * (d_dot + gain * (big_d - rs))
        assert a_mat[0] @ acc - b_vec[0] == pytest.approx(expect, rel=1e-5, abs=1e-5)
        x = (o - p0) @ v0 / speed
        seen["beside" if x < speed**2 / (2 * a_b) else "ahead"] += 1
    assert min(seen.values()) > 30


def test_backup_rows_hold_together_under_the_backup_maneuver():
    """The property the per-point unions lacked: wherever every point's backup barrier is non-negative, braking
    straight along -v at a_b meets all their rows at once (random clouds; the rows are the kernel's)."""
    shield = HOCBFShield(ShieldConfig(barrier="backup", lag_s=0.0))
    cfg = shield.cfg
    checked = 0
    for p, v, pts, cmd in _random_clouds(120, 17):
        if np.any(backup_distance(p - pts, v, cfg.brake_accel) < cfg.r_safe):
            continue
        _, a_mat, b_vec = shield.constraints(pts, p, v, accel_from_command(cmd)[0])
        a_brake = -cfg.brake_accel * v / np.linalg.norm(v)
        assert np.all(a_mat @ a_brake - b_vec >= -1e-9)
        checked += 1
    assert checked > 20


@pytest.mark.parametrize("lag", [False, True])
def test_backup_kernel_rows_equal_the_reference(lag):
    """The numba selection's rows with ``barrier: backup`` are ``backup_rows`` of the selected points (with the lag,
    at the lagged state where that row is the tighter), and both backup and braking (fallback) rows occur."""
    rng = np.random.default_rng(6)
    shield = HOCBFShield(ShieldConfig(barrier="backup", lag_s=0.0))
    cfg = shield.cfg
    backups = rows = 0
    for p, v, pts, cmd in _random_clouds(80, 13):
        a_raw = accel_from_command(cmd)[0]
        lagged = (p + 0.15 * v + rng.normal(0.0, 0.1, 3), v + rng.normal(0.0, 1.0, 3)) if lag else None
        _, a_mat, b_vec = shield.constraints(pts, p, v, a_raw, lagged)
        for o, a_row, b in zip(shield._o_buf[: len(b_vec)], a_mat, b_vec, strict=True):
            cands = [(p, v)] + ([lagged] if lag and (lagged[0] - o) @ (p - o) > 0 else [])
            ref = [backup_rows((ps - o)[None], vs, cfg.r_safe, cfg.brake_accel, cfg.brake_gain) for ps, vs in cands]
            vals = [a_r[0] @ a_raw - b_r[0] for a_r, b_r, _ in ref]
            a_ref, b_ref, u_ref = ref[1] if len(vals) == 2 and vals[1] < vals[0] else ref[0]
            np.testing.assert_allclose(a_row, a_ref[0], rtol=1e-9, atol=1e-9)
            assert b == pytest.approx(b_ref[0], rel=1e-9, abs=1e-9)
            backups += int(u_ref[0])
            rows += 1
    assert rows > 300 and 0 < backups < rows


@pytest.mark.parametrize("gain", [4.0, 16.0])
@pytest.mark.parametrize("offset", [1.0, 0.6, 0.0])
def test_backup_barrier_keeps_speed_beside_obstacles_and_still_stops_head_on(offset, gain):
    """The row of poles of ``test_passing_keeps_speed_beside_obstacles_and_still_stops_head_on`` at 9 m/s, a_raw = 0,
    no lag. Behind the backup barrier at the default gain 4 the vehicle keeps more than 7.8 m/s past poles 1.0 / 0.6 m
    aside (measured 8.6 / 8.0 m/s; the braking barrier: 7.2 / 6.0): while a pole still lies beyond the stopping
    point, the gain-4 approach condition brakes and steers a little, and it passes at least ``offset`` away. At gain
    16 the shield leaves it alone. Head-on it stops outside r_safe at either gain."""
    cfg = ShieldConfig(barrier="backup", lag_s=0.0, memory_steps=0, brake_gain=gain)
    v_min, d_min, active = _fly_past_poles(cfg, offset)
    if offset == 0:
        assert v_min < 0.01 and d_min >= 0.3 - 0.005
    elif gain == 4.0:
        assert 7.8 < v_min < 9.0 and active > 0 and d_min >= offset - 1e-3
    else:
        assert active == 0 and v_min == 9.0 and d_min == pytest.approx(offset, abs=1e-4)


def test_solver_failure_falls_back_to_a_flyable_braking_command():
    """When both QPs fail (a solver error), the shield brakes: a = -2 v, horizontally capped at 0.8 g tan 50 deg.
    A solver cannot be made to fail on purpose, so a subclass stands in for its error (the only stand-in here)."""

    class FailingSolver(HOCBFShield):
        def _qp(self, p, q, g, h):
            return None

    shield = FailingSolver()
    wall_x = 2.0
    ys, zs = np.meshgrid(np.linspace(-2, 2, 21), np.linspace(0.5, 2.5, 11))
    wall = np.stack((np.full(ys.size, wall_x), ys.ravel(), zs.ravel()), 1)
    cmd = np.array([[G / math.cos(0.3), 0.0, 0.3, 0.0]])  # accelerating towards the wall at 6 m/s
    out = shield.filter(cmd, np.array([[0.0, 0.0, 1.5]]), np.array([[6.0, 0.0, 0.0]]), points_w=[wall])
    assert out.status[0] == STATUS_FALLBACK and out.active[0]
    cap = 0.8 * G * math.tan(math.radians(50.0))  # 9.35 m/s^2 < 2 * 6 = 12
    np.testing.assert_allclose(out.accel_safe[0], [-cap, 0.0, 0.0], atol=1e-9)
    assert np.all(np.isfinite(out.command))


def test_kept_braking_rows_give_the_cloud_check_exactly():
    """The selection keeps every considered point's braking rows (their b does not depend on the acceleration), and
    the active-set check reads them: at any acceleration it must return the same smallest row value and the same
    row, to the last bit, as the check that recomputes every point (``min_margin``), with and without the lag
    (including points the lagged prediction has passed, which keep their current row only)."""
    from shield_nav.safety.rows import _rows_min_margin

    rng = np.random.default_rng(3)
    shield = HOCBFShield(ShieldConfig())
    checked = 0
    for p, v, pts, cmd in _random_clouds(60, 7):
        a_raw = accel_from_command(cmd)[0]
        for lagged in (None, (p + 0.6 * v + rng.normal(0.0, 0.3, 3), v + rng.normal(0.0, 2.0, 3))):
            shield.constraints(pts, p, v, a_raw, lagged)
            n = int(shield._rows_n[0])
            assert 0 < n <= len(pts)
            for a in (a_raw, a_raw + rng.normal(0.0, 5.0, 3)):
                kept_row, full_row = np.zeros(4), np.zeros(4)
                kept = _rows_min_margin(shield._rows, n, a, kept_row)
                full = shield.min_margin(pts, p, v, a, lagged)
                full_row[:] = shield._row_buf
                assert kept == full and np.array_equal(kept_row, full_row)
                checked += 1
    assert checked == 240
    distance = HOCBFShield(ShieldConfig(**DIST))
    p, v, pts, cmd = next(iter(_random_clouds(1, 7)))
    distance.constraints(pts, p, v, accel_from_command(cmd)[0])
    assert distance._rows_n[0] == -1  # the distance barrier keeps no rows: its check recomputes them


def test_bench_lockstep_replay_filters_each_shield_as_alone():
    # The cost bench replays the recorded states through two shields in turn; each keeps its own memory and
    # velocity history, so its activity and corrections are those of a replay on its own.
    from shield_nav.bench.shield import PAPER_FORMULATION, record, replay, replay_interleaved

    states = record(duration=0.6)
    cfgs = {"default": ShieldConfig(), "paper": ShieldConfig(**PAPER_FORMULATION)}
    both = replay_interleaved({k: HOCBFShield(c) for k, c in cfgs.items()}, states, repeats=1)
    for name, cfg in cfgs.items():
        _, total, active = replay(HOCBFShield(cfg), states, repeats=1)
        assert len(both[name][1]) == len(total) == len(states)
        np.testing.assert_array_equal(both[name][2], active)
    assert both["default"][2].any() and both["paper"][2].any()
    assert not np.array_equal(both["default"][2], both["paper"][2])


# ---------------------------------------------------------------------------- choosing among the policy's hypotheses
HYP = {"barrier": "distance", "alpha0": 1.0, "alpha1": 2.0, "lag_s": 0.0, "r_safe": 0.5, "min_altitude": 0.0,
       "memory_steps": 0}  # fmt: skip
"""Gains small enough that a point 1.5 m above the vehicle constrains ordinary vertical accelerations."""


def _climb(a_z, yaw=0.0):
    """A level command whose acceleration is (0, 0, a_z): f_n = g + a_z, no tilt."""
    return np.array([G + a_z, 0.0, 0.0, yaw])


def test_hypotheses_first_clean_flies_the_first_candidate_that_breaks_no_row():
    # Vehicle at rest at z = 1.5, one point 1.5 m above it: r = p - o = (0, 0, -1.5), B = 2.25 - 0.25 = 2, Bdot = 0,
    # so the row is 2 r.a + 2|v|^2 + a1 Bdot + a0 B = -3 a_z + 2 >= 0, i.e. a_z <= 2/3.
    # Candidates a_z = 2 (margin -4), 1 (-1), 0.5 (+0.5), 0 (+2): the first clean one is a_z = 0.5.
    pos, vel, pts = np.array([[0.0, 0.0, 1.5]]), np.zeros((1, 3)), [np.array([[0.0, 0.0, 3.0]])]
    cmd = _climb(2.0)[None]
    alts = np.array([[_climb(1.0), _climb(0.5), _climb(0.0)]])
    out = HOCBFShield(ShieldConfig(**HYP, hypotheses="first_clean")).filter(cmd, pos, vel, points_w=pts,
                                                                          alternatives=alts)  # fmt: skip
    assert out.choice[0] == 2 and not out.active[0]
    assert np.array_equal(out.command[0], alts[0, 1])  # flown as the policy gave it, bit for bit
    np.testing.assert_allclose(out.accel_raw[0], [0.0, 0.0, 0.5], atol=1e-12)
    # "top" (the default) ignores the alternatives: the policy's choice, projected onto a_z <= 2/3.
    top = HOCBFShield(ShieldConfig(**HYP)).filter(cmd, pos, vel, points_w=pts, alternatives=alts)
    assert top.choice[0] == 0 and top.active[0]
    np.testing.assert_allclose(top.accel_safe[0], [0.0, 0.0, 2.0 / 3.0], atol=1e-9)
    # A clean top candidate is flown unchanged whatever the alternatives.
    clean = HOCBFShield(ShieldConfig(**HYP, hypotheses="first_clean")).filter(
        _climb(0.0)[None], pos, vel, points_w=pts, alternatives=alts)  # fmt: skip
    assert clean.choice[0] == 0 and not clean.active[0] and np.array_equal(clean.command[0], _climb(0.0))


def test_hypotheses_when_none_is_clean_first_clean_corrects_the_top_and_safest_the_best_margin():
    # Same point: candidates a_z = 2 (margin -4, yaw 0), 1.5 (-2.5, yaw 0.1), 1 (-1, yaw 0.2); all break the row.
    pos, vel, pts = np.array([[0.0, 0.0, 1.5]]), np.zeros((1, 3)), [np.array([[0.0, 0.0, 3.0]])]
    cmd = _climb(2.0)[None]
    alts = np.array([[_climb(1.5, 0.1), _climb(1.0, 0.2)]])
    first = HOCBFShield(ShieldConfig(**HYP, hypotheses="first_clean")).filter(cmd, pos, vel, points_w=pts,
                                                                            alternatives=alts)  # fmt: skip
    assert first.choice[0] == 0 and first.active[0] and first.command[0, 3] == 0.0
    np.testing.assert_allclose(first.accel_safe[0], [0.0, 0.0, 2.0 / 3.0], atol=1e-9)
    safest = HOCBFShield(ShieldConfig(**HYP, hypotheses="safest")).filter(cmd, pos, vel, points_w=pts,
                                                                        alternatives=alts)  # fmt: skip
    assert safest.choice[0] == 2 and safest.active[0]
    np.testing.assert_allclose(safest.accel_raw[0], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(safest.accel_safe[0], [0.0, 0.0, 2.0 / 3.0], atol=1e-9)
    assert safest.command[0, 3] == 0.2  # the corrected command keeps the chosen candidate's yaw
    np.testing.assert_allclose(accel_from_command(safest.command)[0], [0.0, 0.0, 2.0 / 3.0], atol=1e-9)


def test_hypotheses_screen_the_altitude_rows_too():
    # No obstacle point; the ground row at 0.35 m with a0 = 1, a1 = 2, vehicle at rest at z = 0.5:
    # a_z >= -a1 v_z - a0 (z - 0.35) = -0.15. Candidate a_z = -1 breaks it, a_z = -0.1 does not.
    cfg = ShieldConfig(**{**HYP, "min_altitude": 0.35}, hypotheses="first_clean")
    out = HOCBFShield(cfg).filter(_climb(-1.0)[None], np.array([[0.0, 0.0, 0.5]]), np.zeros((1, 3)),
                                  points_w=[np.zeros((0, 3))], alternatives=np.array([[_climb(-0.1)]]))  # fmt: skip
    assert out.choice[0] == 1 and not out.active[0]


def test_hypotheses_input_and_config_errors():
    shield = HOCBFShield(ShieldConfig(**HYP, hypotheses="first_clean"))
    pos, vel, pts = np.zeros((2, 3)), np.zeros((2, 3)), [np.zeros((0, 3))] * 2
    cmd = np.array([_climb(0.0), _climb(0.0)])
    with pytest.raises(ValueError, match=r"alternatives must be \(N, J, 4\)"):
        shield.filter(cmd, pos, vel, points_w=pts, alternatives=np.zeros((1, 2, 4)))
    bad = np.array([[_climb(0.0)], [_climb(0.0)]])
    bad[1, 0, 2] = np.inf
    with pytest.raises(ValueError, match=r"alternative command for vehicle index\(es\) \[1\]"):
        shield.filter(cmd, pos, vel, points_w=pts, alternatives=bad)
    with pytest.raises(ConfigError, match="hypotheses"):
        load_config(ShieldConfig, overrides=["hypotheses=best"])


def test_median_depth_filter_by_hand():
    from shield_nav.safety.memory import _median_depth

    # A 3 x 4 image: a lone near outlier (1.0) on a 5 m wall, a one-pixel-wide vertical pole (2.0) in column 3,
    # an invalid pixel (0) at (2, 0) and the far range (10) at (0, 0).
    img = np.array([[10.0, 5.0, 5.0, 2.0], [5.0, 1.0, 5.0, 2.0], [0.0, 5.0, 5.0, 2.0]])
    cross, square = np.empty_like(img), np.empty_like(img)
    _median_depth(img, cross, False)
    _median_depth(img, square, True)
    # (1, 1): cross window {5, 5, 1, 5, 5} -> 5; 3 x 3 {10, 5, 5, 5, 1, 5, 5, 5} (the 0 left out) -> 5.
    assert cross[1, 1] == 5.0 and square[1, 1] == 5.0
    # (0, 0): cross {10, 5, 5} -> 5; 3 x 3 {10, 5, 5, 1} -> (5 + 5) / 2.
    assert cross[0, 0] == 5.0 and square[0, 0] == 5.0
    # The pole (1, 3): cross {2, 2, 2, 5} -> (2 + 2) / 2 = 2, kept; 3 x 3 {5, 2, 5, 2, 5, 2} -> (2 + 5) / 2 = 3.5:
    # the square window does not keep a one-pixel line.
    assert cross[1, 3] == 2.0 and square[1, 3] == 3.5
    # The pole's top (0, 3): cross {2, 5, 2} -> 2; 3 x 3 {5, 2, 5, 2} -> 3.5.
    assert cross[0, 3] == 2.0 and square[0, 3] == 3.5
    assert cross[2, 0] == 0.0 and square[2, 0] == 0.0  # invalid stays invalid
    # (2, 1): cross {1, 5, 5} (the 0 left out) -> 5.
    assert cross[2, 1] == 5.0
    # Against numpy's median over the valid window on a random image with holes.
    rng = np.random.default_rng(3)
    big = rng.uniform(0.5, 9.0, (12, 17))
    big[rng.random(big.shape) < 0.2] = 0.0
    for square_win in (False, True):
        out = np.empty_like(big)
        _median_depth(big, out, square_win)
        for v in range(12):
            for u in range(17):
                if big[v, u] == 0.0:
                    assert out[v, u] == 0.0
                    continue
                win = [big[v + a, u + b] for a in (-1, 0, 1) for b in (-1, 0, 1)
                       if 0 <= v + a < 12 and 0 <= u + b < 17 and (square_win or a == 0 or b == 0)]  # fmt: skip
                assert out[v, u] == pytest.approx(np.median([x for x in win if x > 0.0]))


def test_depth_filter_removes_a_lone_near_outlier_from_the_shields_cloud():
    # A clean wall 6 m ahead, level flight at 5 m/s towards it: the braking barrier leaves the command alone.
    # One pixel reading 1.2 m (a stereo outlier) makes the unfiltered shield brake hard; the median filters drop it.
    cam = CameraConfig()
    depth = np.full((1, 1, cam.height, cam.width), 6.0, dtype=np.float32)
    noisy = depth.copy()
    noisy[0, 0, cam.height // 2, cam.width // 2] = 1.2
    cmd, pos, vel = np.array([[G, 0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.5]]), np.array([[5.0, 0.0, 0.0]])
    r_wb = np.eye(3)[None]
    base = {"memory_steps": 0, "map_seconds": 0.0, "lag_s": 0.0, "min_altitude": 0.0}
    for filt in ("none", "median_cross", "median_3x3"):
        sh = HOCBFShield(ShieldConfig(depth_filter=filt, **base), cam)
        clean = sh.filter(cmd, pos, vel, depth=depth, R_wb=r_wb)
        sh.reset()
        out = sh.filter(cmd, pos, vel, depth=noisy, R_wb=r_wb)
        assert not clean.active[0]
        # braking barrier at 1.2 m: sqrt(2 * 10 * 0.9) = 4.2 m/s of closing speed allowed < 5: the row binds
        assert out.active[0] == (filt == "none")
        if filt == "none":
            assert out.accel_safe[0, 0] < -5.0
    with pytest.raises(ConfigError, match="depth_filter"):
        ShieldConfig(depth_filter="gauss").validate()
