"""The sampling tracker (shield_nav.algorithms.mppi): rollouts, clamps, weights and warm starts against hand values."""

import math

import numpy as np
import pytest

from envs.config import ConfigError, load_config, stored_config
from envs.fields import scene_field_stack
from envs.navigation import NavigationEnv
from envs.scenes import Box, Scene
from shield_nav.algorithms.baselines import BaselineConfig
from shield_nav.algorithms.expert import PlannerController
from shield_nav.algorithms.expert_config import ExpertConfig
from shield_nav.algorithms.mppi import MppiTracker, clamp_inputs, path_integral_mean, rollout_costs
from shield_nav.algorithms.preview import discretise

# One box in a small room: its +x face is the plane x = 4.5 for |y| < 1 (floor at z = 0, no ceiling).
SCENE = Scene(bounds_lo=(0.0, -3.0, 0.0), bounds_hi=(9.0, 3.0, 3.0),
              primitives=(Box((5.0, 0.0, 1.5), (0.5, 1.0, 1.5)),))  # fmt: skip


@pytest.fixture(scope="module")
def esdf_fields():
    stack = scene_field_stack([SCENE], 0.1, 0.2, lazy=False)
    return stack, stack.kernel_fields(np.zeros(2, dtype=np.int64))[:7]


def _costs(fields, x0, u, ref_p, ref_v, z_cap=None, **w):
    tau, dt = 0.2, 0.04
    a_m, b, e = discretise(tau, dt)
    n, s = u.shape[:2]
    out = np.empty((n, s))
    kw = {"q_pos": 1.0, "q_vel": 0.3, "r_acc": 0.001, "w_clear": 400.0, "clearance": 0.5, "w_crash": 1000.0}
    kw.update(w)
    clearance = np.broadcast_to(np.asarray(kw["clearance"], dtype=float), (n,)).copy()
    rollout_costs(x0, u, np.zeros((n, 3)), ref_p, ref_v, a_m, b, e, kw["q_pos"], kw["q_vel"], kw["r_acc"],
                  kw["w_clear"], clearance, kw["w_crash"], 0.2, fields, out,
                  np.full(n, np.inf) if z_cap is None else np.asarray(z_cap, dtype=float))  # fmt: skip
    return out


def test_a_rollout_in_free_space_costs_its_closed_form_tracking_error(esdf_fields):
    """From rest, input u held: a = u (1 - e^{-t/tau}), v = u (t - tau (1 - e^{-t/tau})), p integrated by hand."""
    _, fields = esdf_fields
    tau, dt, steps, u = 0.2, 0.04, 10, 3.0
    p0 = np.array([1.5, -2.0, 1.5])  # 2.1 m from the box, 1.5 m above the floor: no clearance cost
    x0 = np.zeros((2, 3, 3))
    x0[:, :, 0] = p0
    seq = np.zeros((2, 1, steps, 3))
    seq[0, 0, :, 0] = u  # env 0 accelerates along +x; env 1 hovers
    ref_p = np.repeat(p0[None, None], 2, axis=0).repeat(steps, axis=1)  # the reference stays at the start
    ref_v = np.zeros((2, steps, 3))
    out = _costs(fields, x0, seq, ref_p, ref_v)
    t = dt * np.arange(1, steps + 1)
    q = np.exp(-t / tau)
    v = u * (t - tau * (1 - q))
    p = u * (t**2 / 2 - tau * t + tau**2 * (1 - q))
    want = np.sum(1.0 * p**2 + 0.3 * v**2 + 0.001 * u**2)
    assert out[0, 0] == pytest.approx(want, rel=1e-9)
    assert out[1, 0] == pytest.approx(0.0, abs=1e-12)


def test_clearance_and_crash_costs_read_the_esdf(esdf_fields):
    """Hovering 0.3 m and 0.1 m in front of the box's face: (0.5 - d)^2 x 400 per step, + 1000 within 0.2 m."""
    stack, fields = esdf_fields
    steps = 3
    x0 = np.zeros((2, 3, 3))
    x0[0, :, 0] = (4.2, 0.0, 1.5)
    x0[1, :, 0] = (4.4, 0.0, 1.5)
    d = stack.esdf(np.zeros(2, dtype=np.int64), x0[:, :, 0])
    np.testing.assert_allclose(d, [0.3, 0.1], atol=0.02)  # the field against the face's plane by hand
    ref_p = np.repeat(x0[:, None, :, 0], steps, axis=1)
    out = _costs(fields, x0, np.zeros((2, 1, steps, 3)), ref_p, np.zeros((2, steps, 3)))
    np.testing.assert_allclose(out[:, 0], steps * (400.0 * (0.5 - d) ** 2 + np.array([0.0, 1000.0])), rtol=1e-9)


def test_each_env_reads_its_own_clearance_threshold(esdf_fields):
    """Both envs hover 0.3 m in front of the box's face: threshold 0.5 pays (0.5 - d)^2 x 400 per step, threshold
    0.3 (the narrow field's) about nothing, and neither is within the 0.2 m radius."""
    stack, fields = esdf_fields
    steps = 3
    x0 = np.zeros((2, 3, 3))
    x0[:, :, 0] = (4.2, 0.0, 1.5)
    d = stack.esdf(np.zeros(2, dtype=np.int64), x0[:, :, 0])
    ref_p = np.repeat(x0[:, None, :, 0], steps, axis=1)
    out = _costs(fields, x0, np.zeros((2, 1, steps, 3)), ref_p, np.zeros((2, steps, 3)), clearance=[0.5, 0.3])
    want = steps * 400.0 * np.maximum(np.array([0.5, 0.3]) - d, 0.0) ** 2
    np.testing.assert_allclose(out[:, 0], want, rtol=1e-9, atol=1e-12)
    assert out[0, 0] == pytest.approx(steps * 400.0 * 0.2**2, rel=0.25) and out[1, 0] < 0.05 * out[0, 0]


def test_a_height_cap_counts_as_a_ceiling_in_the_clearance_and_crash_terms(esdf_fields):
    """Hovering in free space (ESDF >= 1 m: 1.5 m above the floor, 2.1 m from the box) under a cap 0.3 m and 0.1 m
    above: (0.5 - 0.3)^2 x 400 = 16 per step, and (0.5 - 0.1)^2 x 400 + 1000 = 1064 within the 0.2 m radius; no cap
    (inf) or a cap far above costs nothing."""
    _, fields = esdf_fields  # the fields index two envs
    steps = 4
    x0 = np.zeros((2, 3, 3))
    x0[:, :, 0] = (1.5, -2.0, 1.5)
    ref_p = np.repeat(x0[:, None, :, 0], steps, axis=1)
    hover = np.zeros((2, 1, steps, 3))
    out = _costs(fields, x0, hover, ref_p, np.zeros((2, steps, 3)), z_cap=[1.8, 1.6])
    np.testing.assert_allclose(out[:, 0], [steps * 16.0, steps * 1064.0], rtol=1e-9)
    out = _costs(fields, x0, hover, ref_p, np.zeros((2, steps, 3)), z_cap=[np.inf, 5.0])
    np.testing.assert_allclose(out[:, 0], [0.0, 0.0], atol=1e-12)


def test_clamp_inputs_to_the_vertical_limit_then_the_tilt_cone():
    u = np.array([[20.0, 0.0, 0.0], [3.0, 4.0, 9.0], [1.0, 0.0, -2.0]])
    out = clamp_inputs(u, 9.81, 45.0, 5.0)
    np.testing.assert_allclose(out[0], [9.81, 0.0, 0.0])  # tan 45 deg = 1: |u_xy| <= g
    np.testing.assert_allclose(out[1], [3.0, 4.0, 5.0])  # |u_xy| = 5 <= 14.81 after u_z clipped to 5
    np.testing.assert_allclose(out[2], [1.0, 0.0, -2.0])
    assert math.hypot(*clamp_inputs(np.array([[30.0, 30.0, -5.0]]), 9.81, 45.0, 5.0)[0, :2]) == pytest.approx(4.81)


def test_path_integral_weights_by_hand():
    """Costs 0, 1, 2 (median 1, least 0), temperature 1: weights e^0, e^-1, e^-2 over constant sequences 0, 1, 2."""
    u = np.arange(3, dtype=float)[None, :, None, None] * np.ones((1, 3, 2, 3))
    w = np.exp(-np.arange(3.0))
    got = path_integral_mean(u, np.array([[0.0, 1.0, 2.0]]), 1.0)
    np.testing.assert_allclose(got, np.full((1, 2, 3), (w @ np.arange(3.0)) / w.sum()))
    # Scale-free: ten times the costs give the same weights; a tiny temperature picks the best sample.
    np.testing.assert_allclose(path_integral_mean(u, np.array([[0.0, 10.0, 20.0]]), 1.0), got)
    np.testing.assert_allclose(path_integral_mean(u, np.array([[5.0, 1.0, 9.0]]), 1e-3), np.ones((1, 2, 3)))
    with pytest.raises(FloatingPointError, match=r"\(env, sample\) \[0, 1\]"):
        path_integral_mean(u, np.array([[0.0, np.nan, 1.0]]), 1.0)
    with pytest.raises(ValueError, match="temperature"):
        path_integral_mean(u, np.zeros((1, 3)), 0.0)


def test_warm_start_advances_the_plan_and_restarts_fresh_episodes():
    m = MppiTracker(tau=0.2, dt=0.04, steps=4, samples=8, seed=0)
    nominal = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    first = m.warm_start(nominal, np.array([5, 7]), 0.01)
    np.testing.assert_allclose(first, np.repeat(nominal[:, None], 4, axis=1))  # no plan yet: the nominal held
    m.plan = np.arange(4, dtype=float)[None, :, None] * np.ones((2, 4, 3))  # inputs 0, 1, 2, 3
    out = m.warm_start(nominal, np.array([6, 0]), 0.01)  # env 1's episode restarted
    np.testing.assert_allclose(out[0, :, 0], [0.25, 1.25, 2.25, 3.0])  # a quarter interval later, the end held
    np.testing.assert_allclose(out[1], np.repeat(nominal[1:2], 4, axis=0))
    m.reset()
    np.testing.assert_allclose(m.warm_start(nominal, np.array([9, 9]), 0.01), first)


def test_candidates_hold_the_base_the_nominal_and_piecewise_constant_noise():
    m = MppiTracker(tau=0.2, dt=0.04, steps=6, samples=5, seed=1)
    base = np.zeros((2, 6, 3))
    nominal = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    c = m.candidates(base, nominal, sigma=2.0, sigma_z=0.0, hold=4)
    assert c.shape == (2, 5, 6, 3)
    np.testing.assert_array_equal(c[:, 0], base)
    np.testing.assert_array_equal(c[:, 1], np.repeat(nominal[:, None], 6, axis=1))
    noise = c[:, 2:]
    np.testing.assert_array_equal(noise[:, :, 1:4], noise[:, :, :1].repeat(3, axis=2))  # held over 4 intervals
    np.testing.assert_array_equal(noise[:, :, 5], noise[:, :, 4])
    assert np.all(noise[..., 2] == 0.0) and np.all(noise[..., :2] != 0.0)
    again = MppiTracker(tau=0.2, dt=0.04, steps=6, samples=5, seed=1).candidates(base, nominal, 2.0, 0.0, 4)
    np.testing.assert_array_equal(again, c)  # seeded: a flight repeats
    assert not np.array_equal(m.candidates(base, nominal, 2.0, 0.0, 4), c)  # the generator moves on
    m.reset()
    np.testing.assert_array_equal(m.candidates(base, nominal, 2.0, 0.0, 4), c)  # and restarts at a reset


def test_mppi_keys_are_checked_by_name():
    ExpertConfig(tracker="mppi").validate()
    for key, bad in (("mppi_samples", 2), ("mppi_steps", 0), ("mppi_hold", 0), ("mppi_temperature", 0.0),
                     ("mppi_w_clear", -1.0), ("mppi_sigma", 0.0)):  # fmt: skip
        with pytest.raises(ConfigError, match=key):
            ExpertConfig(tracker="mppi", **{key: bad}).validate(prefix="baselines.expert.")
    with pytest.raises(ConfigError, match="mppi_narrow_clearance"):
        ExpertConfig(mppi_narrow_clearance=-0.1).validate(prefix="baselines.expert.")


def _nav_env(n: int, speed: float, **over) -> NavigationEnv:
    kw = {"scenes.indices": [0, 1], "episode.initial_speed_fraction": [0.3, 0.5], "episode.target_speeds": [speed],
          "episode.speed_range": [], **over}  # fmt: skip
    env = NavigationEnv(num_envs=n, **kw)
    env.reset(seed=3)
    return env


def test_below_tops_caps_each_env_at_its_scene_top_plus_the_radius():
    env = _nav_env(3, 5.0)
    top = np.array([float(env.scenes[k].bounds_hi[2]) for k in env.scene_id_buf])
    radius = env.cfg.vehicle.airframe.collision_radius
    capped = PlannerController(BaselineConfig(expert=ExpertConfig(mppi_below_tops=True)))
    np.testing.assert_allclose(capped._z_cap(env), top + radius)
    assert np.isinf(PlannerController(BaselineConfig(expert=ExpertConfig()))._z_cap(env)).all()
    cmd = capped.commands(env)  # the capped tracker runs end to end and gives finite commands
    assert cmd.shape == (3, 4) and np.isfinite(cmd).all()


def test_with_vanishing_noise_the_first_command_is_the_preview_trackers():
    """No plan yet and noise ~0: every sample is the preview command held (clamped to the flyable set), so their
    weighted mean is that command. Checked at cruise, after 1.2 s flown by the preview expert; without route
    hysteresis, so both plan the same path from the same state."""
    env = _nav_env(4, 5.0)
    prev = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="preview", commit_dist=0.0)))
    for _ in range(120):
        env.step(np.zeros((4, 4)), commands=prev.commands(env))
    cmd_p = prev.commands(env)
    quiet = ExpertConfig(tracker="mppi", commit_dist=0.0, mppi_sigma=1e-9, mppi_sigma_z=0.0)
    mppi = PlannerController(BaselineConfig(expert=quiet))
    cmd_m = mppi.commands(env)
    assert not mppi.fallback.any()
    ec = ExpertConfig()
    want = clamp_inputs(prev.last["a"], env.cfg.vehicle.gravity, ec.max_tilt_deg, ec.mppi_vert_accel)
    np.testing.assert_allclose(mppi.last["a"], want, atol=1e-6)
    inside = np.all(np.abs(want - prev.last["a"]) < 1e-12, axis=1)  # where the clamp did not act: the same command
    assert inside.any()
    np.testing.assert_allclose(cmd_m[inside], cmd_p[inside], atol=1e-6)
    assert mppi.mppi.plan.shape == (4, ec.mppi_steps, 3)


def _maze_env(n: int) -> NavigationEnv:
    """Benchmark scene 14, a box maze: with 0.5 m of inflation every env descends the narrow field."""
    env = NavigationEnv(num_envs=n, **{"scenes.family": "benchmark", "scenes.indices": [14], "render_depth": False,
                                       "curriculum.enabled": False, "episode.target_speeds": [5.0],
                                       "episode.speed_range": []})  # fmt: skip
    env.reset(seed=2)
    return env


def test_narrow_field_envs_fly_the_sampled_command_with_narrow_tangent_off():
    """``narrow_tangent: true`` (until 2026-12-03): the maze's envs get the tangent command. ``false`` (the default)
    with vanishing noise: their command is the preview tracker's (clamped), as in the open scenes."""
    env = _maze_env(3)
    tangent = PlannerController(BaselineConfig(expert=ExpertConfig(commit_dist=0.0, narrow_tangent=True)))
    tangent.commands(env)
    assert tangent.fallback.all()
    quiet = {"commit_dist": 0.0, "mppi_sigma": 1e-9, "mppi_sigma_z": 0.0}
    prev = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="preview", narrow_tangent=False,
                                                                commit_dist=0.0)))  # fmt: skip
    prev.commands(env)
    mppi = PlannerController(BaselineConfig(expert=ExpertConfig(tracker="mppi", narrow_tangent=False, **quiet)))
    mppi.commands(env)
    assert mppi.fallback.all() and prev.fallback.all()
    ec = ExpertConfig()
    want = clamp_inputs(prev.last["a"], env.cfg.vehicle.gravity, ec.max_tilt_deg, ec.mppi_vert_accel)
    np.testing.assert_allclose(mppi.last["a"], want, atol=1e-6)
    assert np.abs(tangent.last["a"] - mppi.last["a"]).max() > 0.1  # the tangent command is another one
    # ... and it is the tangent rule's: v_ref = v_r unit(P[k+2] - P[k]) + k_x (P[k] - (p + v lag))
    last, ec = tangent.last, tangent.ec
    rows, k = np.arange(3), tangent.last["k_ref"]
    p0, p1 = last["path"][rows, k], last["path"][rows, k + ec.tangent_span]
    pos, vel = env.local_pos, env.vehicles.vel_w
    expect = last["speed"][rows, k, None] * (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
    np.testing.assert_allclose(last["v_ref"], expect + ec.k_x * (p0 - (pos + vel * ec.lag_s)), rtol=1e-9, atol=1e-12)


def test_a_config_written_before_narrow_tangent_keeps_the_tangent_command_in_the_mazes():
    stored = stored_config(ExpertConfig, {"tracker": "mppi", "commit_dist": 1.0})
    assert stored["narrow_tangent"] is True and ExpertConfig().narrow_tangent is False
    assert load_config(BaselineConfig, overrides={"expert": stored}).expert.narrow_tangent is True


def test_narrow_field_envs_read_the_narrow_clearance_threshold():
    """Same seed, same state: on the narrow field, moving ``mppi_clearance`` does not change the sampled command,
    moving ``mppi_narrow_clearance`` does (the threshold enters the rollout costs of those envs only)."""
    env = _maze_env(3)

    def first_command(**kw):
        ctrl = PlannerController(BaselineConfig(expert=ExpertConfig(narrow_tangent=False, commit_dist=0.0, **kw)))
        ctrl.commands(env)
        assert ctrl.fallback.all()
        return ctrl.last["a"]

    base = first_command()
    np.testing.assert_array_equal(first_command(mppi_clearance=2.0), base)
    assert np.abs(first_command(mppi_narrow_clearance=2.0) - base).max() > 1e-3
