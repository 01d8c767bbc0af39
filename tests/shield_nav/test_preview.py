"""The preview tracker (shield_nav.algorithms.preview): model, LQ gains, timed reference against hand and scipy."""

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from envs.config import ConfigError, load_config
from envs.navigation import NavigationEnv
from shield_nav.algorithms.baselines import BaselineConfig
from shield_nav.algorithms.expert import PlannerController
from shield_nav.algorithms.expert_config import ExpertConfig
from shield_nav.algorithms.expert_paths import drag_accel
from shield_nav.algorithms.preview import PreviewGains, discretise, prediction, timed_reference


def _env(n: int, speed: float) -> NavigationEnv:
    env = NavigationEnv(num_envs=n, **{"scenes.indices": [0, 1], "episode.initial_speed_fraction": [0.3, 0.5],
                                       "episode.target_speeds": [speed], "episode.speed_range": []})  # fmt: skip
    env.reset(seed=3)
    return env


def test_discretise_matches_the_closed_form_step():
    """p' = v, v' = a + d, a' = (u - a) / tau over dt with u, d held: the hand-integrated solution."""
    tau, dt = 0.2, 0.05
    a_m, b, e = discretise(tau, dt)
    x0, u, d = np.array([0.3, 2.0, -1.5]), 4.0, -0.7
    x1 = a_m @ x0 + b * u + e * d
    q = math.exp(-dt / tau)
    a1 = q * x0[2] + (1 - q) * u
    # v(t) = v0 + integral of a: a(t) = u + (a0 - u) exp(-t / tau)
    v1 = x0[1] + u * dt + (x0[2] - u) * tau * (1 - q) + d * dt
    p1 = x0[0] + x0[1] * dt + u * dt**2 / 2 + (x0[2] - u) * tau * (dt - tau * (1 - q)) + d * dt**2 / 2
    np.testing.assert_allclose(x1, [p1, v1, a1], rtol=1e-12, atol=1e-12)


def test_prediction_matrices_equal_a_step_by_step_rollout():
    tau, dt, steps = 0.15, 0.04, 7
    phi, gamma, psi = prediction(tau, dt, steps)
    a_m, b, e = discretise(tau, dt)
    rng = np.random.default_rng(0)
    x, u, d = rng.normal(size=3), rng.normal(size=steps), 0.4
    y = phi @ x + gamma @ u + psi * d
    for k in range(steps):
        x = a_m @ x + b * u[k] + e * d
        np.testing.assert_allclose(y[2 * k : 2 * k + 2], x[:2], rtol=1e-10, atol=1e-12)


def _rollout_cost_residuals(u, x0, ref, d, u_prev, tau, dt, w):
    """Residuals whose squares sum to the module's cost, from a plain step-by-step rollout."""
    a_m, b, e = discretise(tau, dt)
    q_pos, q_vel, r_acc, r_jerk = w
    res, x, prev = [], x0.copy(), u_prev
    for k, uk in enumerate(u):
        x = a_m @ x + b * uk + e * d
        res += [math.sqrt(q_pos) * (x[0] - ref[2 * k]), math.sqrt(q_vel) * (x[1] - ref[2 * k + 1])]
        res += [math.sqrt(r_acc) * uk, math.sqrt(r_jerk) * (uk - prev)]
        prev = uk
    return np.array(res)


@pytest.mark.parametrize("w", [(1.0, 0.3, 0.001, 0.003), (2.0, 0.0, 0.01, 0.0), (0.5, 1.0, 0.0, 0.02)])
def test_first_input_minimises_the_cost_as_scipy_does(w):
    """The closed-form first input equals the first input of scipy's minimiser of the same cost."""
    tau, dt, steps = 0.2, 0.04, 12
    gains = PreviewGains.build(tau, dt, steps, *w)
    rng = np.random.default_rng(3)
    x0, ref, d, u_prev = rng.normal(size=3), rng.normal(size=2 * steps) * 2.0, -0.8, 1.3
    args = (x0, ref, d, u_prev, tau, dt, w)
    sol = least_squares(_rollout_cost_residuals, np.zeros(steps), args=args, method="lm", xtol=1e-15, ftol=1e-15)
    # The residuals are affine in u: their exact least-squares minimiser from unit-vector differences.
    r0 = _rollout_cost_residuals(np.zeros(steps), *args)
    jac = np.stack([_rollout_cost_residuals(np.eye(steps)[j], *args) - r0 for j in range(steps)], axis=1)
    exact = np.linalg.lstsq(jac, -r0, rcond=None)[0]
    assert sol.x[0] == pytest.approx(exact[0], abs=1e-5)  # the two minimisers agree
    u0 = gains.first_input(ref, x0, np.array(d), np.array(u_prev))
    assert u0 == pytest.approx(exact[0], abs=1e-9)


def test_a_reachable_reference_is_tracked_with_its_own_input():
    """No input weight, a jerk weight: a reference the model flies with a constant u* from the state now (whose
    thrust acceleration is already u*) costs nothing with u = u*, so the first input is u*."""
    tau, dt, steps = 0.2, 0.04, 15
    a_m, b, e = discretise(tau, dt)
    u_star, d = 2.5, -0.6
    x = np.array([0.0, 3.0, u_star])
    ref = []
    for _ in range(steps):
        x = a_m @ x + b * u_star + e * d
        ref += [x[0], x[1]]
    gains = PreviewGains.build(tau, dt, steps, 1.0, 0.3, 0.0, 0.01)
    u0 = gains.first_input(np.array(ref), np.array([0.0, 3.0, u_star]), np.array(d), np.array(u_star))
    assert u0 == pytest.approx(u_star, abs=1e-9)


def test_gains_refuse_bad_weights():
    with pytest.raises(ValueError, match="steps"):
        PreviewGains.build(0.2, 0.04, 0, 1.0, 0.3, 0.001, 0.003)
    with pytest.raises(ValueError, match="r_acc"):
        PreviewGains.build(0.2, 0.04, 5, 1.0, 0.3, 0.0, 0.0)
    with pytest.raises(ValueError, match="tau"):
        discretise(0.0, 0.04)


def _straight(n_samples: int, ds: float) -> np.ndarray:
    s = ds * np.arange(n_samples)
    return np.stack((s, np.zeros_like(s), np.full_like(s, 1.5)), axis=1)[None]


def test_timed_reference_at_cruise_moves_at_the_profile_speed():
    path = _straight(60, 0.25)
    pos, vel = timed_reference(path, np.full((1, 60), 4.0), np.array([4.0]), 8.0, 0.05, 10)
    t = 0.05 * np.arange(1, 11)
    np.testing.assert_allclose(pos[0, :, 0], 4.0 * t, atol=1e-9)
    np.testing.assert_allclose(pos[0, :, 1:], [[0.0, 1.5]] * 10, atol=1e-12)
    np.testing.assert_allclose(vel[0], [[4.0, 0.0, 0.0]] * 10, atol=1e-9)


def test_timed_reference_from_rest_accelerates_then_cruises():
    """From rest at accel a under a cap V: s(t) = a t^2 / 2 until t = V / a, then V (t - V / (2 a))."""
    ds, a, cap = 0.02, 8.0, 4.0
    path = _straight(400, ds)
    pos, vel = timed_reference(path, np.full((1, 400), cap), np.array([0.0]), a, 0.05, 20)
    t = 0.05 * np.arange(1, 21)
    s = np.where(t < cap / a, a * t**2 / 2, cap * (t - cap / (2 * a)))
    np.testing.assert_allclose(pos[0, :, 0], s, atol=0.01)
    np.testing.assert_allclose(vel[0, :, 0], np.minimum(a * t, cap), atol=0.1)


def test_timed_reference_stops_at_the_paths_end():
    path = _straight(5, 0.5)  # 2 m long
    pos, vel = timed_reference(path, np.full((1, 5), 3.0), np.array([3.0]), 8.0, 0.1, 12)
    t = 0.1 * np.arange(1, 13)
    np.testing.assert_allclose(pos[0, :, 0], np.minimum(3.0 * t, 2.0), atol=1e-9)
    np.testing.assert_allclose(vel[0, t > 2.0 / 3.0 + 1e-9, 0], 0.0)


def test_preview_tracker_commands_the_gains_first_input():
    """tracker: preview: the expert's acceleration is the LQ first input for its plan timed from the vehicle's
    speed along it, and the vehicle's position, velocity and thrust acceleration, with the nominal drag."""
    env = _env(n=4, speed=5.0)
    env.vehicles.vel_w[:] = np.array([3.0, 0.4, 0.0])
    ec = ExpertConfig(tracker="preview")
    ctrl = PlannerController(BaselineConfig(expert=ec))
    ctrl.commands(env)
    last = ctrl.last
    veh = env.vehicles
    a_thr = veh.R_wb[:, :, 2] * veh.motor_thrust_buf.sum(axis=1, keepdims=True) / veh.nominal_mass
    a_thr[:, 2] -= env.cfg.vehicle.gravity
    path = last["path"]
    ahead = path[:, ec.tangent_span] - path[:, 0]
    ahead /= np.linalg.norm(ahead, axis=1, keepdims=True)
    along = np.maximum((veh.vel_w * ahead).sum(axis=1), 0.0)  # the speed along the path, not |v|
    assert np.all(along < np.linalg.norm(veh.vel_w, axis=1))
    ref_p, ref_v = timed_reference(path, last["speed"], along, ec.preview_accel, ec.preview_dt,
                                   ec.preview_steps)  # fmt: skip
    gains = PreviewGains.build(ec.preview_tau, ec.preview_dt, ec.preview_steps, ec.preview_q_pos, ec.preview_q_vel,
                               ec.preview_r_acc, ec.preview_r_jerk)  # fmt: skip
    drag = drag_accel(veh.vel_w, veh.R_wb, env.cfg.vehicle.airframe)
    assert not ctrl.fallback.any()  # open training scenes: every env flies the inflated field
    for i in range(4):
        for ax in range(3):
            ref = np.stack((ref_p[i, :, ax], ref_v[i, :, ax]), axis=1).reshape(-1)
            x0 = np.array([env.local_pos[i, ax], veh.vel_w[i, ax], a_thr[i, ax]])
            u = gains.first_input(ref, x0, drag[i, ax], a_thr[i, ax])
            assert last["a"][i, ax] == pytest.approx(u, abs=1e-9)


@pytest.mark.parametrize("tracker", ["preview", "mppi"])
def test_preview_tracker_hands_the_narrow_field_to_the_tangent_tracker(tracker):
    """Where the inflated field closes the way (benchmark scene 14, a box maze) the expert descends the narrow field;
    with ``narrow_tangent: true`` (the behaviour until 2026-12-03) the preview tracker's command there, and the
    sampling tracker's round it, is the tangent tracker's (the default flies its own: tests/shield_nav/test_mppi.py)."""
    env = NavigationEnv(num_envs=4, **{"scenes.family": "benchmark", "scenes.indices": [14], "render_depth": False,
                                       "curriculum.enabled": False})  # fmt: skip
    env.reset(seed=2)
    env.vehicles.vel_w[:] = np.array([1.0, -0.5, 0.0])
    prev = PlannerController(BaselineConfig(expert=ExpertConfig(tracker=tracker, narrow_tangent=True)))
    cmd_p = prev.commands(env)
    tang = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="tangent")))
    cmd_t = tang.commands(env)
    assert prev.fallback.all()
    np.testing.assert_allclose(prev.last["path"], tang.last["path"], atol=1e-12)
    np.testing.assert_allclose(cmd_p, cmd_t, atol=1e-12)
    np.testing.assert_allclose(prev.last["a"], tang.last["a"], atol=1e-12)


@pytest.mark.parametrize(("tracker", "speed", "least"), [("preview", 5.0, 3.0), ("mppi", 7.0, 4.0)])
def test_preview_tracker_flies_the_open_scenes(tracker, speed, least):
    """Real physics: the preview expert (and the sampling one round it, at 7 m/s) leaves the start and flies 1.5 s on
    the open training scenes without touching anything."""
    env = _env(n=4, speed=speed)
    ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(tracker=tracker)))
    start = env.local_pos.copy()
    for _ in range(150):
        cmd = ctrl.commands(env)
        assert np.isfinite(cmd).all()
        env.step(np.zeros((4, 4)), commands=cmd)
    assert not env.vehicles.collided_buf.any()
    assert np.all(np.linalg.norm(env.local_pos - start, axis=1) > least)


def test_preview_weights_without_a_minimiser_name_the_key():
    with pytest.raises(ConfigError, match="expert.preview_r_acc"):
        load_config(BaselineConfig, overrides={"expert.preview_r_acc": 0.0, "expert.preview_r_jerk": 0.0})
