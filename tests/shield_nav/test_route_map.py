"""The onboard route map (``shield_nav.route_map``) on the real env: marking, planning, steering by hand."""

import math

import numpy as np
import pytest

from envs.config import ConfigError
from envs.navigation import NavigationEnv
from shield_nav.route_map import OnboardRoute, RouteMapConfig

QUIET = {"scenes.indices": [0], "randomization.att_noise_std_deg": 0.0, "randomization.vel_noise_std": 0.0}


@pytest.fixture(scope="module")
def env():
    e = NavigationEnv(num_envs=2, **QUIET)
    pinned = {
        "scene_ids": np.zeros(2, np.int64),
        "start": np.array([[2.0, 0.0, 1.5], [2.0, 3.0, 1.5]]),
        "goal": np.array([[30.0, 0.0, 1.5], [8.0, 5.0, 1.5]]),
        "speed": np.full(2, 3.0),
        "yaw": np.array([0.0, 0.7]),
    }
    e.first_obs, _ = e.reset(seed=0, options=pinned)
    return e


def test_with_the_carrot_at_the_goal_the_state_is_the_envs_own(env):
    """Nothing mapped: the carrot is the goal and ``goal_xy_h`` equals the env's (one goal beyond 10 m, one within)."""
    route = OnboardRoute(RouteMapConfig(), env.cfg.camera)
    route.reset(env)
    for occ in route.occ:
        occ[:] = False  # forget the first image: an empty map
    state = env.first_obs["state"]
    out = route.steer(env, state)
    np.testing.assert_array_equal(route.carrot, env.goal_buf[:, :2])
    np.testing.assert_allclose(out, state, rtol=0, atol=1e-12)
    # By hand: env 0 flies yaw 0 with its goal 28 m ahead (unit x); env 1's goal is (6, 2) away at yaw 0.7.
    np.testing.assert_allclose(out[0, 16:18], [1.0, 0.0], atol=1e-2)
    d = np.array([6.0, 2.0]) - (env.local_pos[1, :2] - [2.0, 3.0])
    psi = math.atan2(env.vehicles.R_wb[1, 1, 0], env.vehicles.R_wb[1, 0, 0])
    want = np.array([math.cos(psi) * d[0] + math.sin(psi) * d[1], -math.sin(psi) * d[0] + math.cos(psi) * d[1]]) / 10
    np.testing.assert_allclose(out[1, 16:18], want, atol=1e-9)


def test_a_depth_wall_marks_the_cells_at_its_distance(env):
    """A constant 4 m depth image of a level camera is a wall 4 m ahead: only cells at x = camera x + 4 are marked."""
    route = OnboardRoute(RouteMapConfig(cell=0.25), env.cfg.camera)
    route.reset(env)
    saved = env.sensor_depth_buf.copy()
    try:
        env.sensor_depth_buf[:] = 4.0
        for occ in route.occ:
            occ[:] = False
        route.observe(env)
    finally:
        env.sensor_depth_buf[:] = saved
    ij = np.argwhere(route.occ[0])
    assert len(ij) > 0
    x = route.lo[0, 0] + 0.25 * ij[:, 0]
    # Camera at the body origin (plus its mount offset along x, under 0.2 m), level within the hover's tilt.
    assert np.all(np.abs(x - (env.local_pos[0, 0] + 4.0)) <= 0.25 + 0.2)
    half_width = 4.0 * math.tan(math.radians(env.cfg.camera.hfov_deg / 2))
    y = route.lo[0, 1] + 0.25 * ij[:, 1]
    assert y.max() - y.min() == pytest.approx(2 * half_width, abs=0.6)


def test_the_route_turns_to_the_gap_of_a_mapped_wall(env):
    """A wall across the way at x = 6 m with its only gap at y = +4..+6: the carrot heads for the gap (y > 0)."""
    cfg = RouteMapConfig(cell=0.25, inflate=0.5, lookahead=6.0)
    route = OnboardRoute(cfg, env.cfg.camera)
    route.reset(env)
    occ = route.occ[0]
    occ[:] = False
    gx = route.lo[0, 0] + 0.25 * np.arange(occ.shape[0])
    gy = route.lo[0, 1] + 0.25 * np.arange(occ.shape[1])
    wall_x = np.argmin(np.abs(gx - (env.local_pos[0, 0] + 4.0)))
    occ[wall_x, (gy < 4.0) | (gy > 6.0)] = True
    carrot = route.plan(env, 0)
    assert carrot[1] > 1.5  # towards the gap, not straight at the goal (y = 0)
    # The route descends a geodesic field: 6 m of it from the start ends within the 6 m disc round the vehicle.
    assert np.linalg.norm(carrot - env.local_pos[0, :2]) <= 6.0 + 0.25
    # Without the wall the carrot lies on the straight line to the goal, 6 m on (to the grid's 8 directions).
    occ[:] = False
    occ[0, 0] = True  # a far corner cell, so the planner runs
    straight = route.plan(env, 0)
    assert abs(straight[1] - env.local_pos[0, 1]) <= 0.25 and straight[0] > env.local_pos[0, 0] + 5.5


def test_bad_settings_name_their_key():
    with pytest.raises(ConfigError, match="route_map.inflate"):
        OnboardRoute(RouteMapConfig(inflate=0.0), None)
    with pytest.raises(ConfigError, match="route_map.z_max"):
        OnboardRoute(RouteMapConfig(z_min=2.0, z_max=1.0), None)
