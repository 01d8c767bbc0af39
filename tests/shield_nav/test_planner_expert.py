"""The planning expert (shield_nav.algorithms.expert): speed profile, curvature, paths, commands against hand values."""

import math

import numpy as np
import pytest

from envs.config import ConfigError, load_config, stored_config
from envs.navigation import NavigationEnv
from envs.vehicle.config import AirframeConfig
from shield_nav.algorithms.baselines import BaselineConfig, PlannerExpert, make_baseline
from shield_nav.algorithms.expert import (
    ExpertConfig,
    PlannerController,
    drag_accel,
    resample_ahead,
    speed_profile,
    visible_samples,
    windowed_curvature,
    yaw_within,
)

SMALL = {"scenes.indices": [0, 1], "episode.initial_speed_fraction": [0.3, 0.5]}


def test_speed_profile_brakes_into_a_slow_sample_by_hand():
    # Straight path (kappa 0), cap 9 m/s except 2 m/s at sample 6; a = 4 m/s^2, ds = 0.5 m: 2 a ds = 4.
    cap = np.full((1, 10), 9.0)
    cap[0, 6] = 2.0
    v = speed_profile(np.zeros((1, 10)), cap, lat_accel=8.0, brake_accel=4.0, ds=0.5, min_speed=0.5)[0]
    expect = [math.sqrt(x) for x in (28.0, 24.0, 20.0, 16.0, 12.0, 8.0)] + [2.0, 9.0, 9.0, 9.0]
    np.testing.assert_allclose(v, expect, rtol=1e-12)


def test_speed_profile_curvature_cap_and_floor():
    # kappa 2 1/m with 8 m/s^2 lateral: sqrt(8 / 2) = 2 m/s; a huge kappa is floored at min_speed.
    kappa = np.array([[0.0, 2.0, 1e6, 0.0]])
    v = speed_profile(kappa, np.full((1, 4), 9.0), lat_accel=8.0, brake_accel=1e6, ds=0.1, min_speed=0.7)[0]
    np.testing.assert_allclose(v[1:3], [2.0, 0.7])


def test_speed_profile_with_a_budget_is_unchanged_on_a_straight_path():
    # No curvature: the budget (10) exceeds brake_accel (4), so the braking is brake_accel's, as by hand above.
    cap = np.full((1, 10), 9.0)
    cap[0, 6] = 2.0
    v = speed_profile(np.zeros((1, 10)), cap, lat_accel=8.0, brake_accel=4.0, ds=0.5, min_speed=0.5,
                      accel_budget=10.0)[0]  # fmt: skip
    expect = [math.sqrt(x) for x in (28.0, 24.0, 20.0, 16.0, 12.0, 8.0)] + [2.0, 9.0, 9.0, 9.0]
    np.testing.assert_allclose(v, expect, rtol=1e-12)


def test_speed_profile_friction_circle_by_hand():
    # kappa 0.25, 0.25, 1 1/m, lateral 4 m/s^2 = the budget: curvature caps 4, 4, 2 m/s. ds 0.1 m, brake_accel 10.
    kappa = np.array([[0.25, 0.25, 1.0]])
    cap = np.full((1, 3), 9.0)
    # Separate budgets: v1 = sqrt(2^2 + 2 * 10 * 0.1) = sqrt(6), v0 = sqrt(6 + 2) = sqrt(8).
    v = speed_profile(kappa, cap.copy(), lat_accel=4.0, brake_accel=10.0, ds=0.1, min_speed=0.5)[0]
    np.testing.assert_allclose(v, [math.sqrt(8.0), math.sqrt(6.0), 2.0], rtol=1e-12)
    # Shared budget 4: segment 1-2 has kappa max(0.25, 1) = 1 and 2^2 * 1 = 4 m/s^2 of turning, nothing left to
    # brake with, so v1 = 2; segment 0-1 has kappa 0.25, turning 2^2 * 0.25 = 1, braking sqrt(16 - 1) = sqrt(15):
    # v0 = sqrt(4 + 2 * sqrt(15) * 0.1).
    v = speed_profile(kappa, cap.copy(), lat_accel=4.0, brake_accel=10.0, ds=0.1, min_speed=0.5, accel_budget=4.0)[0]
    np.testing.assert_allclose(v, [math.sqrt(4.0 + 0.2 * math.sqrt(15.0)), 2.0, 2.0], rtol=1e-12)


@pytest.mark.parametrize("radius", [2.0, 5.0])
def test_windowed_curvature_of_a_circle_is_one_over_its_radius(radius):
    ds = 0.1
    th = np.arange(0, 60) * ds / radius
    circle = np.stack((radius * np.sin(th), radius * (1 - np.cos(th)), np.zeros_like(th)), axis=1)[None]
    k = windowed_curvature(circle, 3)[0]
    # Chord lengths shorten the arc slightly: within 0.5 % of 1/R away from the ends.
    np.testing.assert_allclose(k[5:-5], 1.0 / radius, rtol=5e-3)
    line = np.stack((np.arange(20) * 0.3, np.zeros(20), np.ones(20)), axis=1)[None]
    np.testing.assert_allclose(windowed_curvature(line, 3), 0.0, atol=1e-6)


def _env(n=8, speed=7.0):
    env = NavigationEnv(num_envs=n, **SMALL, **{"episode.target_speeds": [speed], "episode.speed_range": []})
    env.reset(seed=3)
    return env


def test_paths_descend_the_inflated_geodesic_field_and_keep_clearance():
    env = _env()
    raw = PlannerController(BaselineConfig(expert=ExpertConfig(smooth_window=1, band_iters=0))).plan(env)["path"]
    np.testing.assert_allclose(np.linalg.norm(np.diff(raw, axis=1), axis=2), 0.35, rtol=1e-9)  # steps of ds
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(band_iters=0)))  # the moving average alone
    plan = ctrl.plan(env)
    path, speed = plan["path"], plan["speed"]
    ec = ctrl.ec
    assert path.shape == (8, int(math.ceil(ec.horizon / ec.ds)) + 1, 3)
    np.testing.assert_allclose(path[:, 0], env.local_pos)
    # Smoothing is a 7-sample moving average inside (where it keeps clearance): check one interior sample by hand.
    k = 10
    avg = raw[:, k - 3 : k + 4].mean(axis=1)
    ok = np.isclose(path[:, k], avg).all(axis=1) | np.isclose(path[:, k], raw[:, k]).all(axis=1)
    assert ok.all()
    # Phi of the episode's anchor field, independently queried, falls along every path.
    stack, anchors, _ = ctrl._fields(env)
    ids = np.repeat(env.scene_id_buf, path.shape[1])
    phi = anchors.geodesic(ids, np.repeat(env.anchor_buf, path.shape[1]), path.reshape(-1, 3)).reshape(8, -1)
    assert np.all(phi[:, -1] < phi[:, 0] - 0.8 * ec.horizon)
    # The traced clearance is the env's own ESDF, and paths stay out of the obstacles.
    np.testing.assert_allclose(plan["clear"], env.field_stack.esdf(ids, path.reshape(-1, 3)).reshape(8, -1))
    assert plan["clear"].min() > env.cfg.vehicle.airframe.collision_radius
    # The profile never exceeds the target speed and can brake between consecutive samples.
    assert np.all(speed <= 7.0 + 1e-12)
    assert np.all(speed[:, :-1] ** 2 <= speed[:, 1:] ** 2 + 2 * ec.brake_accel * ec.ds + 1e-9)


def test_a_height_weight_plans_on_height_weighted_anchor_fields_and_keeps_the_paths_lower():
    """``high_weight`` > 0: the expert's Phi is that of anchor fields built with ``height_cost=(high_ref, weight)``
    (rebuilt independently here), and its paths from the same states keep lower than without it."""
    from envs.fields import scene_field_stack
    from envs.fields.anchors import GoalAnchorFields

    env = _env()
    ec = ExpertConfig(band_iters=0, high_weight=1.0, high_ref=1.0)
    ctrl = PlannerController(BaselineConfig(expert=ec))
    _, anchors, _ = ctrl._fields(env)
    assert anchors.height_cost == (1.0, 1.0)
    stack = scene_field_stack(env.scenes, env.cfg.scenes.field_resolution, ec.field_radius)
    ref = GoalAnchorFields(env.scenes, stack, env.anchor_fields.count, height_cost=(1.0, 1.0))
    pts = np.random.default_rng(0).uniform(env.scenes[0].bounds_lo, env.scenes[0].bounds_hi, (64, 3))
    ids, k = np.zeros(64, dtype=np.int64), np.full(64, int(env.anchor_buf[0]))
    np.testing.assert_allclose(anchors.geodesic(ids, k, pts), ref.geodesic(ids, k, pts))
    low = ctrl.plan(env)["path"][..., 2]
    plain = PlannerController(BaselineConfig(expert=ExpertConfig(band_iters=0))).plan(env)["path"][..., 2]
    assert low.mean() < plain.mean() - 0.1 and (low.max(axis=1) <= plain.max(axis=1) + 1e-9).all()
    with pytest.raises(ConfigError, match="high_weight"):
        ExpertConfig(high_weight=-1.0).validate(prefix="baselines.expert.")
    bare = NavigationEnv(num_envs=2, **SMALL, **{"episode.goal_anchors": 0})
    bare.reset(seed=3)
    with pytest.raises(ValueError, match="high_weight needs goal anchor fields"):
        ctrl._fields(bare)


def test_band_moves_samples_to_the_neighbours_midpoint_by_hand_in_free_space():
    """One band iteration with band_step 1 far from every obstacle (no push): each inner sample is the midpoint of its
    neighbours before the iteration; a straight, evenly spaced path stays put; the end samples never move."""
    env = _env(n=1)
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(band_iters=1, band_step=1.0, band_clearance=0.0)))
    ctrl.fallback = np.zeros(1, dtype=bool)
    zig = np.array([[0.0, 0.0, 0.0], [1.0, 0.4, 0.0], [2.0, -0.2, 0.0], [3.0, 0.6, 0.1], [4.0, 0.0, 0.0]])
    path = env.local_pos[:, None, :] + zig[None]
    clear = env.field_stack.esdf(np.repeat(env.scene_id_buf, 5), path.reshape(-1, 3)).reshape(1, 5)
    out, d = ctrl._band(env, path, clear)
    expect = path.copy()
    expect[0, 1:-1] = 0.5 * (path[0, :-2] + path[0, 2:])
    np.testing.assert_allclose(out, expect, atol=1e-12)
    np.testing.assert_allclose(d, env.field_stack.esdf(np.repeat(env.scene_id_buf, 5), out.reshape(-1, 3))[None])
    line = env.local_pos[:, None, :] + np.arange(5)[None, :, None] * np.array([0.3, 0.1, 0.0])
    np.testing.assert_allclose(ctrl._band(env, line, clear)[0], line, atol=1e-12)


def test_band_straightens_paths_and_keeps_its_floor_of_clearance():
    """On real paths: first and last samples stay, no sample ends closer to an obstacle than min(band_clearance,
    its clearance before the band), the reported clearance is the env's ESDF, and the curvature falls."""
    env = _env()
    plain = PlannerController(BaselineConfig(expert=ExpertConfig(band_iters=0)))
    before = plain.plan(env)
    ctrl = PlannerController(BaselineConfig())  # the default: 10 iterations
    after = ctrl.plan(env)
    p0, p1 = before["path"], after["path"]
    np.testing.assert_allclose(p1[:, [0, -1]], p0[:, [0, -1]])
    assert not np.allclose(p1, p0)
    floor = np.where(ctrl.fallback, env.cfg.vehicle.airframe.collision_radius + ctrl.ec.smooth_slack, 0.5)[:, None]
    assert np.all(after["clear"] >= np.minimum(floor, before["clear"]) - 1e-9)
    d = env.field_stack.esdf(np.repeat(env.scene_id_buf, p1.shape[1]), p1.reshape(-1, 3)).reshape(p1.shape[:2])
    np.testing.assert_allclose(after["clear"], d)
    assert after["kappa"].mean() < 0.9 * before["kappa"].mean()


def _band_numpy(env, fallback, ec, path, clear):
    """The elastic band in numpy over envs (the expert's formulation until 2026-12-03): the reference the kernel must
    equal to the bit."""
    n, kp1, _ = path.shape
    ids = np.repeat(env.scene_id_buf, kp1)
    floor = np.where(fallback, env.cfg.vehicle.airframe.collision_radius + ec.smooth_slack, ec.band_clearance)
    floor = floor[:, None]
    p, d = path.copy(), clear.copy()
    for _ in range(ec.band_iters):
        q = p.copy()
        q[:, 1:-1] += ec.band_step * (0.5 * (p[:, :-2] + p[:, 2:]) - p[:, 1:-1])
        dq = env.field_stack.esdf(ids, q.reshape(-1, 3)).reshape(n, kp1)
        grad = env.field_stack.esdf_grad(ids, q.reshape(-1, 3)).reshape(n, kp1, 3)
        push = np.maximum(floor - dq, 0.0)
        push[:, [0, -1]] = 0.0
        q += push[..., None] * (grad / np.maximum(np.linalg.norm(grad, axis=-1, keepdims=True), 1e-9))
        dq = env.field_stack.esdf(ids, q.reshape(-1, 3)).reshape(n, kp1)
        ok = dq >= np.minimum(floor, d) - 1e-9
        p, d = np.where(ok[..., None], q, p), np.where(ok, dq, d)
    return p, d


@pytest.mark.parametrize(("band_clearance", "narrow"), [(0.5, False), (0.9, False), (0.5, True)])
def test_band_kernel_equals_the_numpy_band_to_the_bit(band_clearance, narrow):
    """The compiled band (``_band_kernel``) against the numpy formulation on the expert's raw paths through clutter,
    with a floor that pushes many samples (0.9 m) and with every env on the narrow field's floor: identical arrays."""
    env = _env()
    ec = ExpertConfig(band_clearance=band_clearance)
    ctrl = PlannerController(BaselineConfig(expert=ec))
    raw = PlannerController(BaselineConfig(expert=ExpertConfig(smooth_window=1, band_iters=0))).plan(env)
    ctrl.fallback = np.full(env.num_envs, narrow)
    path, clear = raw["path"], raw["clear"]
    p_ref, d_ref = _band_numpy(env, ctrl.fallback, ec, path, clear)
    p, d = ctrl._band(env, path, clear)
    assert not np.array_equal(p, path)  # the band moved samples
    np.testing.assert_array_equal(p, p_ref)
    np.testing.assert_array_equal(d, d_ref)
    np.testing.assert_array_equal(raw["path"], path)  # inputs untouched


def test_a_config_written_before_band_iters_flies_without_the_band():
    """The band came on by default on 2026-12-03 (10 iterations); a stored config that lacks the key (written before
    it existed) means no band, and a stored value is kept."""
    assert ExpertConfig().band_iters == 10
    stored = stored_config(ExpertConfig, {"tracker": "tangent", "commit_dist": 0.0})
    assert stored["band_iters"] == 0
    assert load_config(BaselineConfig, overrides={"expert": stored}).expert.band_iters == 0
    assert stored_config(ExpertConfig, {"band_iters": 3})["band_iters"] == 3


def test_resample_ahead_by_hand():
    """A straight polyline along x and an L: samples k ds beyond the foot, the offset removed over ``blend``."""
    line = np.stack((np.arange(11.0), np.zeros(11), np.zeros(11)), axis=1)[None]
    out, d, reach = resample_ahead(np.array([[2.3, 0.4, 0.0]]), line, m=3, ds=0.5, blend=2)
    np.testing.assert_allclose(out[0], [[2.3, 0.4, 0.0], [2.8, 0.2, 0.0], [3.3, 0.0, 0.0], [3.8, 0.0, 0.0]])
    np.testing.assert_allclose(d, [0.4])
    assert reach.tolist() == [True]
    assert resample_ahead(np.array([[2.3, 0.4, 0.0]]), line, m=20, ds=0.5, blend=2)[2].tolist() == [False]
    ell = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]])
    out, d, reach = resample_ahead(np.array([[0.5, 0.0, 0.0]]), ell, m=3, ds=0.5, blend=1)
    np.testing.assert_allclose(out[0], [[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.5, 0.0], [1.0, 1.0, 0.0]], atol=1e-12)
    assert d.tolist() == [0.0] and reach.tolist() == [True]


def _fly(ctrl, env, steps):
    for _ in range(steps):
        env.step(np.zeros((env.num_envs, 4)), commands=ctrl.commands(env))


def test_committed_path_follows_the_remembered_one_then_descends_again():
    """commit_dist 2 m (6 samples of 0.35 m, blend 1.5 m = 4 samples), gates wide open: after a step, an env that
    commits flies the vehicle's position, then exactly the remembered path resampled ahead of it, then the tail; its
    reported clearance is the ESDF and keeps the fresh trace's floor. The first call has nothing to remember."""
    env = _env()
    ec = ExpertConfig(commit_dist=2.0, commit_max_dev=10.0, commit_slack=100.0)
    ctrl = PlannerController(BaselineConfig(expert=ec))
    env.step(np.zeros((env.num_envs, 4)), commands=ctrl.commands(env))
    assert not ctrl.committed.any()
    env.step(np.zeros((env.num_envs, 4)), commands=ctrl.commands(env))
    prev = ctrl.last["path"].copy()
    fresh = PlannerController(BaselineConfig()).plan(env)
    plan = ctrl.plan(env)
    took = ctrl.committed
    assert took.any()
    head, _, _ = resample_ahead(env.local_pos, prev, 6, ec.ds, 4)
    path = plan["path"]
    np.testing.assert_allclose(path[:, 0], env.local_pos)
    np.testing.assert_allclose(path[took, 1:7], head[took, 1:], atol=1e-12)
    np.testing.assert_allclose(path[~took], fresh["path"][~took])
    d = env.field_stack.esdf(np.repeat(env.scene_id_buf, path.shape[1]), path.reshape(-1, 3)).reshape(path.shape[:2])
    np.testing.assert_allclose(plan["clear"], d, atol=1e-9)
    floor = np.minimum(fresh["clear"].min(axis=1), ec.field_radius - ec.smooth_slack)
    assert np.all(plan["clear"][took & ~ctrl.fallback].min(axis=1) >= floor[took & ~ctrl.fallback] - 1e-9)


def test_committed_path_gates_reset_and_new_episodes():
    """No commitment after reset(), in an env whose episode started again, or beyond commit_max_dev."""
    env = _env()
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(commit_dist=2.0, commit_slack=100.0)))
    _fly(ctrl, env, 3)
    env.episode_length_buf[:2] = 0  # as if envs 0 and 1 had just been reset
    ctrl.plan(env)
    assert ctrl.committed.tolist() == [False, False] + [True] * 6
    ctrl.plan(env)  # the same state again: no step since the last call
    assert not ctrl.committed.any()
    _fly(ctrl, env, 1)
    ctrl.reset(env)
    ctrl.plan(env)
    assert not ctrl.committed.any()
    tight = PlannerController(BaselineConfig(expert=ExpertConfig(commit_dist=2.0, commit_slack=100.0,
                                                                 commit_max_dev=0.0)))  # fmt: skip
    loose = PlannerController(BaselineConfig(expert=ExpertConfig(commit_dist=2.0, commit_slack=100.0,
                                                                 commit_max_dev=0.1)))  # fmt: skip
    for ctrl, commits in ((tight, False), (loose, True)):
        ctrl.commands(env)  # remembers paths that start at the vehicles
        env.vehicles.pos_w[:] += 0.05  # off the remembered paths by 0.087 m: beyond 0, within 0.1
        env.episode_length_buf[:] += 1  # as if a step had passed
        ctrl.plan(env)
        assert ctrl.committed.all() == commits and ctrl.committed.any() == commits


def _ridge(env, dx=4.0):
    """A point on the ridge between two ways round an obstacle: (env index, y0, y1, states) where the fresh trace
    from ``x + (dx, y0, 0)`` and from 0.1 m beside it, ``y1``, part more than 1.5 m at 4.2 m along, both with a
    clearance of at least 1 m. Scanned over lateral offsets of every env's start from -2 to 2 m."""
    ctrl = PlannerController(BaselineConfig())
    x0 = env.vehicles.pos_w.copy()
    offs = np.arange(-20, 21) * 0.1
    at, clear = [], []
    for o in offs:
        env.vehicles.pos_w[:] = x0 + np.array([dx, o, 0.0])
        plan = ctrl.plan(env)
        at.append(plan["path"][:, 12] - np.array([0.0, o, 0.0]))
        clear.append(plan["clear"][:, 0])
    jump = np.linalg.norm(np.diff(np.array(at), axis=0), axis=2)  # (40, N)
    clear = np.array(clear)
    jump[(clear[:-1] < 1.0) | (clear[1:] < 1.0)] = 0.0
    a, i = np.unravel_index(jump.argmax(), jump.shape)
    assert jump[a, i] > 1.5, "no ridge in the scanned scenes"
    return int(i), x0 + np.array([dx, 0.0, 0.0]), offs[a], offs[a + 1]


def test_velocity_keyed_route_follows_the_side_the_vehicle_moves_to():
    """At a ridge of the geodesic field (found by scanning offsets, ``_ridge``): a vehicle 0.2 m on one side of it
    that moves sideways across it (so ``x + v predict_s`` lies 0.3 m beyond it) flies the other way round, i.e. the
    straight segment to the predicted point and then the fresh trace from there; moving away from the ridge, or with
    ``predict_s`` 0, it flies the fresh trace. The same holds from the other side."""
    env = _env()
    i, base, y0, y1 = _ridge(env)
    ec = ExpertConfig(commit_dist=0.0, predict_s=0.2)
    fresh = PlannerController(BaselineConfig())
    for y_at, y_to in ((y0 - 0.2, y1 + 0.3), (y1 + 0.2, y0 - 0.3)):
        env.vehicles.pos_w[:] = base + np.array([0.0, y_to, 0.0])
        there = fresh.plan(env)["path"][i]  # the fresh trace from the predicted point
        env.vehicles.pos_w[:] = base + np.array([0.0, y_at, 0.0])
        here = fresh.plan(env)["path"][i]
        x = env.local_pos[i].copy()
        for sign in (1.0, -1.0):
            env.vehicles.vel_w[:] = 0.0
            env.vehicles.vel_w[:, 1] = sign * (y_to - y_at) / ec.predict_s
            ctrl = PlannerController(BaselineConfig(expert=ec))
            path = ctrl.plan(env)["path"][i]
            if sign < 0:  # moving away from the ridge: the predicted point is on the same side
                assert not ctrl.committed[i]
                np.testing.assert_allclose(path, here)
                continue
            assert ctrl.committed[i]
            # Sample k lies k ds along the polyline x -> there[0] -> there[1] -> ...: check two by hand.
            gap = np.linalg.norm(there[0] - x)
            assert gap == pytest.approx(0.6)  # 0.2 + 0.1 + 0.3 m
            np.testing.assert_allclose(path[0], x)
            np.testing.assert_allclose(path[1], x + 0.35 / gap * (there[0] - x), atol=1e-12)
            s = 10 * ec.ds - gap  # sample 10 lies that far along the fresh trace from the predicted point
            cum = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(there, axis=0), axis=1))))
            j = np.searchsorted(cum, s) - 1
            expect = there[j] + (s - cum[j]) / (cum[j + 1] - cum[j]) * (there[j + 1] - there[j])
            np.testing.assert_allclose(path[10], expect, atol=1e-9)
            assert np.linalg.norm(path[12] - here[12]) > 1.0  # the other way round
    env.vehicles.vel_w[:, 1] = 5.0
    off = PlannerController(BaselineConfig(expert=ExpertConfig(commit_dist=0.0)))
    np.testing.assert_allclose(off.plan(env)["path"], fresh.plan(env)["path"])


def test_velocity_keyed_route_only_at_or_above_predict_min_speed():
    """``predict_min_speed`` gates the velocity key by each env's target speed: at the ridge, with the vehicle moving
    across it, the env flies the other way round when its target speed is at or above the threshold and the fresh
    trace (the same path as with ``predict_s`` 0) when it is 0.5 m/s below."""
    env = _env()
    i, base, y0, y1 = _ridge(env)
    env.vehicles.pos_w[:] = base + np.array([0.0, y0 - 0.2, 0.0])
    here = PlannerController(BaselineConfig()).plan(env)["path"][i]
    env.vehicles.vel_w[:] = 0.0
    env.vehicles.vel_w[:, 1] = (y1 + 0.3 - (y0 - 0.2)) / 0.2
    gate = 7.0
    for speed, keyed in ((gate, True), (gate + 2.0, True), (gate - 0.5, False)):
        env.target_speed_buf[:] = speed
        ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(commit_dist=0.0, predict_s=0.2,
                                                                    predict_min_speed=gate)))  # fmt: skip
        path = ctrl.plan(env)["path"][i]
        assert bool(ctrl.committed[i]) == keyed
        if keyed:
            assert np.linalg.norm(path[12] - here[12]) > 1.0
        else:
            np.testing.assert_allclose(path, here)


def test_smoothing_passes_repeat_the_moving_average_by_hand():
    """smooth_passes 2: each sample is the 7-sample average of the once-smoothed path (or keeps its once-smoothed
    value where the average would come closer than field_radius - smooth_slack to an obstacle)."""
    env = _env()
    once = PlannerController(BaselineConfig(expert=ExpertConfig(band_iters=0))).plan(env)
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(smooth_passes=2, band_iters=0)))
    twice = ctrl.plan(env)
    p1, p2 = once["path"], twice["path"]
    np.testing.assert_allclose(p2[:, 0], env.local_pos)
    floor = ctrl.ec.field_radius - ctrl.ec.smooth_slack
    moved = 0
    for k in range(3, p1.shape[1] - 3):
        avg = p1[:, k - 3 : k + 4].mean(axis=1)
        took = np.isclose(p2[:, k], avg).all(axis=1)
        kept = np.isclose(p2[:, k], p1[:, k]).all(axis=1)
        assert (took | kept).all()
        moved += int((took & ~kept).sum())
        # A sample that took the average keeps the floor of clearance; the reported clearance is the env's ESDF.
        ids = env.scene_id_buf
        d = env.field_stack.esdf(ids, p2[:, k])
        np.testing.assert_allclose(twice["clear"][:, k], d)
        assert np.all(d[took & ~kept] >= floor - 1e-9)
    assert moved > 0  # the second pass changes the path
    # The second pass straightens the path: its curvature is lower on average.
    assert twice["kappa"].mean() < once["kappa"].mean()


def test_command_at_rest_on_a_straight_path_accelerates_along_it():
    """With v = 0 and no feedforward, a = k_v v_ref: the thrust vector is g e3 + k_v v_r chord (before limits)."""
    env = _env(n=4, speed=3.0)
    env.vehicles.vel_w[:] = 0.0
    cfg = BaselineConfig(expert=ExpertConfig(tracker="chord", ff_gain=0.0, k_v=1.0, max_tilt_deg=59.0))
    ctrl = PlannerController(cfg)
    cmd = ctrl.commands(env)
    v_ref = ctrl.last["v_ref"]
    np.testing.assert_allclose(ctrl.last["a"], 1.0 * v_ref, atol=1e-12)
    # f_n = |a + g e3|, and the yaw is the chord's heading.
    np.testing.assert_allclose(cmd[:, 0], np.linalg.norm(v_ref + [0, 0, 9.81], axis=1), rtol=1e-9)
    np.testing.assert_allclose(cmd[:, 3], np.arctan2(v_ref[:, 1], v_ref[:, 0]), atol=1e-12)
    # At rest the reference is the first sample's planned speed along the chord.
    np.testing.assert_allclose(np.linalg.norm(v_ref, axis=1), ctrl.last["speed"][:, 0], rtol=1e-9)


def test_drag_accel_by_hand():
    """Rotor drag -R diag(d) R^T v plus parasitic drag -rho CdA |v| v / (2 m), for a level and a pitched body."""
    af = AirframeConfig(linear_drag=(0.3, 0.3, 0.1), quadratic_drag_area=0.012, air_density=1.225, mass=1.0)
    level = np.eye(3)
    pitched = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # body z along world x
    vel = np.array([[7.0, 0.0, 0.0], [0.0, -2.0, 0.0], [1.0, 0.0, 0.0]])
    a = drag_accel(vel, np.stack((level, level, pitched)), af)
    q = 0.5 * 1.225 * 0.012  # per unit mass
    expect = np.array(
        [
            [-(0.3 * 7.0 + q * 7.0 * 7.0), 0.0, 0.0],  # 2.46015 m/s^2 against the motion
            [0.0, 0.3 * 2.0 + q * 2.0 * 2.0, 0.0],
            [-(0.1 * 1.0 + q * 1.0), 0.0, 0.0],  # flying along body z meets the z coefficient
        ]
    )
    np.testing.assert_allclose(a, expect, rtol=1e-12, atol=1e-12)


def test_drag_feedforward_adds_the_models_drag_to_the_command():
    """drag_ff w: the commanded acceleration is the plain one minus w times the nominal drag at the current state."""
    env = _env(n=4, speed=7.0)
    env.vehicles.vel_w[:] = np.array([6.0, 0.5, 0.0])
    plain = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="tangent")))  # drag_ff acts on tangent's loop
    plain.commands(env)
    comp = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="tangent", drag_ff=0.5)))
    comp.commands(env)
    drag = drag_accel(env.vehicles.vel_w, env.vehicles.R_wb, env.cfg.vehicle.airframe)
    assert np.all(drag[:, 0] < -1.5)  # ~0.3 * 6 + 0.4: against the motion
    np.testing.assert_allclose(comp.last["a"], plain.last["a"] - 0.5 * drag, rtol=1e-12, atol=1e-12)


def test_drag_feedforward_closes_the_velocity_loops_steady_error():
    """Real physics: on the open training scenes, the velocity loop a = k_v (v_ref - v) settles about drag / k_v
    short of its reference; with the drag feedforward the vehicle holds the reference."""
    errs = {}
    for w in (0.0, 1.0):
        env = _env(n=4, speed=5.0)
        ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="tangent", drag_ff=w, ff_gain=0.0)))
        short = []
        for step in range(250):
            cmd = ctrl.commands(env)
            if step >= 150:  # after the start transient
                v_ref = ctrl.last["v_ref"]
                along = np.einsum("ni,ni->n", env.vehicles.vel_w, v_ref) / np.linalg.norm(v_ref, axis=1)
                short.append(np.linalg.norm(v_ref, axis=1) - along)
            env.step(np.zeros((4, 4)), commands=cmd)
        errs[w] = float(np.mean(short))
    # Drag at 5 m/s: 0.3 * 5 + 0.5 * 1.225 * 0.012 * 25 = 1.68 m/s^2, i.e. ~0.42 m/s short at k_v = 4.
    assert errs[0.0] > 0.25
    assert abs(errs[1.0]) < 0.5 * errs[0.0]


def test_planner_is_a_baseline_row_and_a_dagger_expert():
    env = _env(n=4)
    assert isinstance(make_baseline("expert", BaselineConfig()), PlannerController)
    act = PlannerExpert()(env)
    assert act.shape == (4, 4) and np.all(np.abs(act) <= 1.0) and np.isfinite(act).all()


@pytest.mark.parametrize(("key", "value"), [("horizon", -1.0), ("curv_window", 0), ("max_tilt_deg", 70.0),
                                            ("lag_s", -0.1), ("visibility", "lidar"), ("los_step", 0.0),
                                            ("narrow_clearance", -0.1), ("narrow_weight", -1.0),
                                            ("drag_ff", -0.5), ("smooth_passes", 0), ("band_iters", -1),
                                            ("band_step", 0.0), ("band_clearance", -0.1), ("commit_dist", -1.0),
                                            ("commit_dist", 13.5), ("commit_max_dev", -0.1),
                                            ("commit_blend", -1.0), ("commit_slack", -0.5), ("predict_s", -0.1),
                                            ("predict_min_speed", -1.0), ("route_tol", -0.1),
                                            ("route_span", 0.0), ("preview_tau", 0.0), ("preview_dt", -0.1),
                                            ("preview_steps", 0), ("preview_q_pos", -1.0), ("preview_r_jerk", -0.1),
                                            ("preview_drag", -1.0), ("preview_accel", 0.0),
                                            ("accel_budget", -1.0), ("accel_budget", 5.0)])  # fmt: skip
def test_bad_expert_config_names_the_key(key, value):
    with pytest.raises(ConfigError, match=f"expert.{key}"):
        load_config(BaselineConfig, overrides={f"expert.{key}": value})


def test_velocity_key_and_route_hysteresis_exclude_each_other():
    with pytest.raises(ConfigError, match="expert.predict_s.*commit_dist"):
        load_config(BaselineConfig, overrides={"expert.predict_s": 0.2, "expert.commit_dist": 1.0})
    with pytest.raises(ConfigError, match="expert.predict_min_speed.*predict_s 0"):
        load_config(BaselineConfig, overrides={"expert.predict_min_speed": 8.0, "expert.commit_dist": 0.0})
    assert load_config(BaselineConfig, overrides={"expert.predict_s": 0.2, "expert.commit_dist": 0.0})


def test_flat_inflated_field_falls_back_to_the_envs_own_field():
    """Inflated so much that no way to the goal is left, the inflated Phi is flat (its unreachable cap): the expert
    then descends the narrow field (the env's own traversable space, clearance-weighted), and its path still makes
    progress on the env's field."""
    # Benchmark scene 14 (a maze of boxes): 0.5 m of inflation closes every corridor to the goal region.
    env = NavigationEnv(num_envs=4, **{"scenes.family": "benchmark", "scenes.indices": [14], "render_depth": False,
                                       "curriculum.enabled": False})  # fmt: skip
    env.reset(seed=2)
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(field_radius=0.5, band_iters=0)))
    plan = ctrl.plan(env)
    assert ctrl.fallback.all()
    path = plan["path"]
    ids = np.repeat(env.scene_id_buf, path.shape[1])
    phi = env.anchor_fields.geodesic(ids, np.repeat(env.anchor_buf, path.shape[1]), path.reshape(-1, 3)).reshape(4, -1)
    assert np.all(phi[:, -1] < phi[:, 0] - 0.7 * ctrl.ec.horizon)
    # The narrow field weighs clearance below narrow_clearance: its paths keep more of it than the env's own field's
    # (narrow_clearance 0), and its Phi, a weighted length, is never below the distance.
    plain = PlannerController(BaselineConfig(expert=ExpertConfig(field_radius=0.5, narrow_clearance=0.0, band_iters=0)))
    plain_clear = plain.plan(env)["clear"].min(axis=1)
    assert plain.fallback.all()
    narrow_clear = plan["clear"].min(axis=1)
    assert np.all(narrow_clear > plain_clear) and np.all(narrow_clear >= 0.5)
    # The elastic band (the default) may pull those paths in, but not below the vehicle radius + smooth_slack.
    banded = PlannerController(BaselineConfig(expert=ExpertConfig(field_radius=0.5)))
    band_clear = banded.plan(env)["clear"].min(axis=1)
    r_vehicle = env.cfg.vehicle.airframe.collision_radius
    assert banded.fallback.all() and np.all(band_clear >= r_vehicle + banded.ec.smooth_slack - 1e-9)
    pts = env.local_pos + np.array([5.0, 0.0, 0.0])
    assert np.all(ctrl._phi(env, env.scene_id_buf, env.anchor_buf, pts, own=False)
                  >= env.anchor_fields.geodesic(env.scene_id_buf, env.anchor_buf, pts) - 1e-6)  # fmt: skip
    normal = PlannerController(BaselineConfig())
    normal.plan(_env(n=4))  # training scenes 0-1: open enough for 0.5 m
    assert not normal.fallback.any()


def test_the_flatness_test_is_not_fooled_by_the_lookups_slope_outside_the_scene():
    """At the side or the top of the scene's box the lookup adds the distance out of the box to Phi: across the box's
    face a plateau of the inflated field (its unreachable cap) shows a slope of 0.5, above ``flat_slope``. The test
    keeps its points inside the box, so a vehicle there descends the narrow field instead of a path that never
    leaves it (the stall of session 75 in a validation maze)."""
    env = NavigationEnv(num_envs=3, **{"scenes.family": "benchmark", "scenes.indices": [14], "render_depth": False,
                                       "curriculum.enabled": False})  # fmt: skip
    env.reset(seed=2)
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(field_radius=0.5, band_iters=0)))
    lo, hi = np.array(env.scenes[0].bounds_lo), np.array(env.scenes[0].bounds_hi)

    # Free points on the box's faces (y = lo, y = hi, z = hi) in the maze's middle, vehicle radius + 0.2 m clear.
    def free_point(axis: int, value: float) -> np.ndarray:
        for xq in np.arange(20.0, 44.0, 0.25):
            for c in np.arange(0.5, 2.6, 0.5) if axis == 1 else np.arange(-8.0, 8.0, 0.5):
                p = np.array([xq, value, c]) if axis == 1 else np.array([xq, c, value])
                if env.field_stack.esdf(np.zeros(1, np.int64), p[None])[0] > 0.4:
                    return p
        raise AssertionError(f"no free point on the face {axis} = {value}")

    starts = np.array([free_point(1, lo[1]), free_point(1, hi[1]), free_point(2, hi[2])])
    goal = np.array([[63.5, 0.0, 1.5]] * 3)
    opts = {"scene_ids": np.zeros(3, np.int64), "start": starts, "goal": goal, "speed": np.full(3, 3.0)}
    env.reset(seed=2, options={**opts, "yaw": np.zeros(3)})
    x, h, ids, anchor = env.local_pos, ctrl.ec.fd_step, env.scene_id_buf, env.anchor_buf
    phi = ctrl._phi(env, ids, anchor, x)
    # The inflated field's plateau: its unreachable cap, the largest reachable Phi plus the box's diagonal.
    assert np.allclose(phi, phi[0]) and np.all(phi > np.linalg.norm(hi - lo))
    out = x + np.array([[0.0, -h, 0.0], [0.0, h, 0.0], [0.0, 0.0, h]])  # one step out of the box's face
    assert np.allclose((ctrl._phi(env, ids, anchor, out) - phi) / (2 * h), 0.5)  # what the raw test read: 0.5
    plan = ctrl.plan(env)
    assert ctrl.fallback.all()
    path = plan["path"]
    k = path.shape[1]
    g = env.anchor_fields.geodesic(np.repeat(ids, k), np.repeat(anchor, k), path.reshape(-1, 3)).reshape(3, k)
    assert np.all(g[:, -1] < g[:, 0] - 0.5 * ctrl.ec.horizon)  # the path leaves the edge towards the goal
    # The test as before (flat_test_inside: false, the shipped recipes' teacher; a config written before the key):
    # the slope out of the box keeps those vehicles on the inflated field.
    before = PlannerController(
        BaselineConfig(expert=ExpertConfig(field_radius=0.5, band_iters=0, flat_test_inside=False))
    )
    before.plan(env)
    assert not before.fallback.any()
    assert stored_config(ExpertConfig, {})["flat_test_inside"] is False


def test_tangent_tracker_follows_the_path_direction_by_hand():
    """tracker: tangent: v_ref = v_r unit(P[k+span] - P[k]) + k_x (P[k] - (p + v lag)), with k = round(|v| lag / ds)."""
    env = _env(n=4, speed=5.0)
    ec = ExpertConfig(tracker="tangent", tangent_span=2, k_x=2.0, ff_gain=0.0)
    ctrl = PlannerController(BaselineConfig(expert=ec))
    ctrl.commands(env)
    last = ctrl.last
    pos, vel = env.local_pos, env.vehicles.vel_w
    k = np.clip(np.round(np.linalg.norm(vel, axis=1) * ec.lag_s / ec.ds).astype(int), 0, last["path"].shape[1] - 3)
    np.testing.assert_array_equal(last["k_ref"], k)
    rows = np.arange(4)
    p0, p1 = last["path"][rows, k], last["path"][rows, k + 2]
    expect = last["speed"][rows, k, None] * (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
    expect += 2.0 * (p0 - (pos + vel * ec.lag_s))
    np.testing.assert_allclose(last["v_ref"], expect, rtol=1e-9, atol=1e-12)


def test_yaw_within_moves_a_lead_to_the_range_by_hand():
    """A 90 deg lead held at 60; -3 rad from a base of 3 rad leads by 2 pi - 6 (wrapped), within: kept; -143 deg held
    at -60; a lead across +-pi held at the nearer side (base 3, psi 3 - 2 pi + 1.5 leads by 1.5 rad)."""
    got = yaw_within(np.array([math.pi / 2, -3.0, 0.1 - 2.5, 4.5 - 2 * math.pi]), np.array([0.0, 3.0, 0.1, 3.0]), 60.0)
    np.testing.assert_allclose(got, [math.pi / 3, -3.0, 0.1 - math.pi / 3, 3.0 + math.pi / 3], rtol=1e-12)


def test_yaw_in_action_holds_the_labels_yaw_in_range_and_keeps_the_thrust_vector():
    """With ``yaw_in_action`` the command's yaw leads the yaw base by at most ``action.yaw_range_deg`` and roll and
    pitch are solved at that yaw: the thrust vector f_n R(phi, theta, psi) e3 (built here from the Euler angles) is
    the one the free command flies. Flights whose chord leads by less keep the free command to the bit."""
    from envs.vehicle.rotations import euler_zyx_to_rot

    env = NavigationEnv(num_envs=4, **SMALL, **{"episode.target_speeds": [5.0], "episode.speed_range": []})
    env.reset(seed=3)
    to_goal = np.arctan2(*(env.goal_buf - env.local_pos)[:, 1::-1].T)
    env.reset(seed=3, options={"yaw": to_goal + np.array([0.0, 0.6, 2.0, -2.6])})  # leads of 0, 34, 115, 149 deg
    ec = {"tracker": "tangent", "commit_dist": 0.0}
    free = PlannerController(BaselineConfig(expert=ExpertConfig(**ec))).commands(env)
    held = PlannerController(BaselineConfig(expert=ExpertConfig(yaw_in_action=True, **ec))).commands(env)
    lead = (free[:, 3] - env.yaw_bases + math.pi) % (2 * math.pi) - math.pi
    far = np.abs(lead) > math.radians(env.cfg.action.yaw_range_deg)
    assert far.tolist() == [False, False, True, True]
    np.testing.assert_array_equal(held[~far], free[~far])
    np.testing.assert_allclose(held[far, 3], env.yaw_bases[far] + np.sign(lead[far]) * math.pi / 3, atol=1e-12)
    assert np.abs(held[far, 1:3] - free[far, 1:3]).max() > 0.05  # the attitude is another one ...

    def thrust(c):
        return c[:, 0, None] * euler_zyx_to_rot(c[:, 1], c[:, 2], c[:, 3])[:, :, 2]

    np.testing.assert_allclose(thrust(held), thrust(free), atol=1e-9)  # ... with the same thrust vector
    act = env.command_to_action(held)
    assert np.abs(act[:, 3]).max() <= 1.0 + 1e-12 and np.abs(env.command_to_action(free)[far, 3]).min() > 1.0


def test_visible_samples_by_hand():
    """Frustum, range and line of sight for a camera at the origin looking along world +x (87 x 58 deg, 10 m)."""
    from envs.camera import CameraConfig

    cam = CameraConfig()
    R_wc = np.array([[[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]])  # columns: right=-y, down=-z, axis=+x
    samples = [
        (0.0, 0.0, 0.0),  # the vehicle: always seen
        (5.0, 0.0, 0.0),  # straight ahead
        (11.0, 0.0, 0.0),  # beyond the 10 m range
        (5.0, 4.5, 0.0),  # 42.0 deg left: inside the 43.5 deg half field of view
        (5.0, 5.0, 0.0),  # 45.0 deg left: outside
        (5.0, 0.0, 2.5),  # 26.6 deg up: inside the 29 deg half field of view
        (5.0, 0.0, 3.5),  # 35.0 deg up: outside
        (-2.0, 0.0, 0.0),  # behind
        (8.0, -3.0, 0.0),  # 20.6 deg right, but a 0.3 m ball sits on its line of sight at (4, -1.5, 0)
        (8.0, 3.0, 0.0),  # the mirror image: clear
    ]
    path = np.array(samples)[None]
    centre, radius = np.array([4.0, -1.5, 0.0]), 0.3

    def esdf(pts):
        return np.linalg.norm(pts - centre, axis=-1) - radius

    seen = visible_samples(path, np.zeros((1, 3)), R_wc, cam, esdf, los_step=0.5)
    assert seen[0].tolist() == [True, True, False, True, False, True, False, False, False, True]
    # A coarse line of sight would step over the ball (points 1.2 m apart); the covering rule still sees it.
    assert not visible_samples(path, np.zeros((1, 3)), R_wc, cam, esdf, los_step=1.5)[0, 8]


def test_camera_visibility_slows_the_profile_before_unseen_path():
    """With visibility 'camera' the caps after the first unseen sample are min_speed, so the profile brakes into it;
    turning the vehicle's back to its path leaves only the vehicle's own sample seen."""
    env = _env(n=4, speed=9.0)
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(visibility="camera")))
    plan = ctrl.plan(env)
    seen, speed, ec = plan["seen"], plan["speed"], ctrl.ec
    assert seen[:, 0].all() and np.all(np.diff(seen.astype(int), axis=1) <= 0)  # a seen prefix
    free = PlannerController(BaselineConfig()).plan(env)["speed"]
    assert np.all(speed <= free + 1e-12)
    np.testing.assert_allclose(speed[~seen], ec.min_speed)
    # facing away from the path (yaw + 180 deg): nothing ahead is seen, the vehicle must crawl from here
    from envs.vehicle.rotations import quat_mul

    env.vehicles.quat_wb[:] = quat_mul(np.array([[0.0, 0.0, 0.0, 1.0]]), env.vehicles.quat_wb.copy())  # yaw by pi
    plan = ctrl.plan(env)
    assert not plan["seen"][:, 1:].any()
    np.testing.assert_allclose(plan["speed"][:, 0], np.sqrt(ec.min_speed**2 + 2 * ec.brake_accel * ec.ds), rtol=1e-9)


def _reference_trace(ctrl, env):
    """The path trace written with numpy over envs (the expert's rule before its numba kernel), for comparison."""
    ec = ctrl.ec
    n, h = env.num_envs, ec.fd_step
    ids, anchor, goal = env.scene_id_buf, env.anchor_buf, env.goal_buf
    k_steps = int(math.ceil(ec.horizon / ec.ds))
    offsets = np.concatenate((np.eye(3) * h, -np.eye(3) * h))
    ids7, anchor7 = np.repeat(ids, 7), np.repeat(anchor, 7)

    def unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)

    def phi7(x, fallback):
        pts = np.concatenate((x[:, None, :], x[:, None, :] + offsets[None]), axis=1).reshape(-1, 3)
        out = ctrl._phi(env, ids7, anchor7, pts).reshape(n, 7)
        if fallback.any():
            out[fallback] = ctrl._phi(env, ids7, anchor7, pts, own=False).reshape(n, 7)[fallback]
        return out

    x = env.local_pos.astype(np.float64).copy()
    p0 = phi7(x, np.zeros(n, dtype=bool))
    fallback = np.abs(p0[:, 1:4] - p0[:, 4:7]).max(axis=1) / (2 * h) < ec.flat_slope
    path, clear, prev = np.empty((n, k_steps + 1, 3)), np.empty((n, k_steps + 1)), None
    for k in range(k_steps + 1):
        path[:, k] = x
        d, grad_d, _ = env.field_stack.query(ids, x, geodesic=False)
        clear[:, k] = d
        if k == k_steps:
            break
        phi = phi7(x, fallback)
        u = -unit(phi[:, 1:4] - phi[:, 4:7])
        g = unit(grad_d)
        g_perp = g - np.sum(g * u, axis=1)[:, None] * u
        w = ec.clearance_gain * np.clip(ec.d_pref - d, 0.0, ec.d_pref) / ec.d_pref
        u = unit(u + w[:, None] * g_perp)
        near = phi[:, 0] < ec.goal_switch
        u[near] = unit(goal[near] - x[near])
        if prev is not None and ec.momentum > 0:
            u = unit(u + ec.momentum * prev)
        prev = u
        x = x + ec.ds * u
    return path, clear, fallback


def test_trace_kernel_equals_a_numpy_trace_with_and_without_the_narrow_field():
    """The numba trace gives the paths and clearances of the same rule written in numpy over envs: in one batch,
    envs on an open scene (the inflated field) and envs in a maze whose 0.5 m inflation closes every corridor (the
    narrow field), then the same envs started 3 m before their goal points (the straight-at-the-goal switch)."""
    env = NavigationEnv(num_envs=6, **{"scenes.family": "benchmark", "scenes.indices": [0, 14], "render_depth": False,
                                       "curriculum.enabled": False})  # fmt: skip
    scenes = np.array([0, 1, 0, 1, 0, 1])
    env.reset(seed=4, options={"scene_ids": scenes})
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(field_radius=0.5, smooth_window=1, band_iters=0)))
    path, clear = ctrl.trace(env)
    ref_path, ref_clear, ref_fallback = _reference_trace(ctrl, env)
    np.testing.assert_array_equal(ref_fallback, scenes == 1)  # the maze's envs, and only they, fall back
    np.testing.assert_array_equal(ctrl.fallback, ref_fallback)
    np.testing.assert_allclose(path, ref_path, atol=1e-6)
    np.testing.assert_allclose(clear, ref_clear, atol=1e-6)

    goal = env.goal_buf.copy()
    env.reset(options={"scene_ids": scenes, "start": goal - np.array([3.0, 0.0, 0.0]), "goal": goal})
    np.testing.assert_allclose(env.goal_buf, goal)
    path, clear = ctrl.trace(env)
    ref_path, ref_clear, _ = _reference_trace(ctrl, env)
    np.testing.assert_allclose(path, ref_path, atol=1e-6)
    np.testing.assert_allclose(clear, ref_clear, atol=1e-6)
    # Within goal_switch of the goal the path heads at the goal point: its last sample is nearer than its first.
    last, first = np.linalg.norm(path[:, -1] - goal, axis=1), np.linalg.norm(path[:, 0] - goal, axis=1)
    assert np.all(last < first)


def test_expert_cost_bench_times_a_variant_and_names_a_bad_key(capsys):
    """``python -m shield_nav.bench expert --set KEY=VALUE`` flies that variant (echoed in the JSON line); a bad key
    is named before any flight."""
    import json

    from shield_nav.bench.expert import main

    res = main(["--steps", "2", "--num-envs", "2", "--json", "--set", "commit_dist=1"])
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["expert"] == {"commit_dist": 1} == res["expert"]
    assert line["num_envs"] == 2 and line["expert_us_per_label"] > 0
    assert line["scenes"] == "ablation:0,1,2,3,4,5,6,7" and line["narrow_share"] == 0.0
    with pytest.raises(SystemExit):
        main(["--steps", "2", "--set", "commit_dits=1"])
    assert "commit_dits" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--steps", "2", "--scenes", "benchmark:16"])
    assert "indices [16] out of range" in capsys.readouterr().err
    # The box mazes: labels there descend the narrow field (0.5 m of inflation closes their corridors).
    maze = main(["--steps", "2", "--num-envs", "2", "--scenes", "benchmark:14"])
    assert maze["scenes"] == "benchmark:14" and 0.0 < maze["narrow_share"] <= 1.0
