"""The navigation task: rewards against hand-computed values, episodes, resets, determinism, gymnasium and rsl-rl."""

import math

import gymnasium
import numpy as np
import pytest
import torch

import envs  # noqa: F401  (registers ShieldNav-v0)
from envs.config import ConfigError
from envs.fields import build_fields
from envs.navigation import REWARD_TERMS, STATE_DIM, NavigationEnv
from envs.navigation import rewards as R
from envs.rsl_rl import RslRlVecEnv
from envs.scenes import Box, Scene

SMALL = {"scenes.indices": [0, 1]}
QUIET = {
    **SMALL,
    "randomization.mass_scale.enabled": False,
    "randomization.inertia_scale.enabled": False,
    "randomization.thrust_scale.enabled": False,
    "randomization.torque_scale.enabled": False,
    "randomization.motor_tau_scale.enabled": False,
    "randomization.gain_scale.enabled": False,
    "randomization.action_latency_steps": [0, 0],
    "randomization.vel_noise_std": 0.0,
    "randomization.att_noise_std_deg": 0.0,
    "randomization.wind_max": 0.0,
    "randomization.gust_std": 0.0,
    "randomization.depth_noise.depth_sigma_coeff": 0.0,
    "randomization.depth_noise.dropout_prob": 0.0,
    "randomization.depth_noise.holes_per_frame": 0.0,
}


# ----------------------------------------------------------------------------- reward terms by hand
def test_reward_terms_hand_computed():
    # Navigation: lambda * clamp(Phi_prev - Phi_now, -C, C) with lambda 2, C 0.2.
    np.testing.assert_allclose(R.navigation(np.array([10.0, 10.0, 10.0]), np.array([9.9, 9.5, 10.4]), 2.0, 0.2),
                               [0.2, 0.4, -0.4])  # fmt: skip
    # Safety: b = d - d_safe; bdot = grad . v; clip(bdot + gamma b, -2, 0).
    # Env 0: d = 1.0, d_safe 0.6 -> b = 0.4; moving away (bdot = +1): 1 + 2*0.4 = 1.8 -> clipped to 0.
    # Env 1: d = 0.7 -> b = 0.1; approaching at 1 m/s along -grad: -1 + 0.2 = -0.8.
    # Env 2: d = 0.3 -> b = -0.3; approaching at 5 m/s: -5 - 0.6 = -5.6 -> clipped to -2.
    grad = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    vel = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, -5.0, 0]])
    np.testing.assert_allclose(R.safety(np.array([1.0, 0.7, 0.3]), grad, vel, 2.0, 0.6, -2.0), [0.0, -0.8, -2.0])
    # Smoothness: -(w |a|^2 + |a - a_prev|^2), w = 0.1: a = (1, 0, 0, 0), a_prev = 0 -> -(0.1 + 1) = -1.1.
    np.testing.assert_allclose(R.smooth(np.array([[1.0, 0, 0, 0]]), np.zeros((1, 4)), 0.1), [-1.1])
    # Speed: -(|v| - v_t)^2 above the target only: |v| = 5 vs 3 -> -4; |v| = 2 -> 0.
    np.testing.assert_allclose(
        R.speed(
            np.array([[3.0, 4.0, 0], [2.0, 0, 0]]),
            np.array([3.0, 3.0]),
        ),
        [-4.0, 0.0],
    )
    # Height band [0.5, 2.5]: z = 0.2 -> -0.3; z = 3.0 -> -0.5; z = 1 -> 0.
    np.testing.assert_allclose(R.height(np.array([0.2, 3.0, 1.0]), 0.5, 2.5), [-0.3, -0.5, 0.0])
    np.testing.assert_array_equal(R.collision(np.array([True, False])), [-1.0, 0.0])
    np.testing.assert_array_equal(R.success(np.array([True, False])), [1.0, 0.0])


def test_geodesic_progress_positive_where_euclidean_is_negative():
    # A wall across the course at x = 30 with a single gap at y in [8, 12]. Flying from (28, 0) towards the gap
    # (+y) moves away from the goal in straight-line terms but along the shortest path around the wall.
    wall = (Box((30.0, -4.0, 1.5), (0.2, 12.0, 1.5)), Box((30.0, 14.0, 1.5), (0.2, 2.0, 1.5)))
    scene = Scene(primitives=wall)
    stack = build_fields(scene, resolution=0.2, vehicle_radius=0.2, use_cache=False).stack()
    goal = np.array([63.5, 0.0, 1.5])
    p0, p1 = np.array([[28.0, 0.0, 1.5]]), np.array([[28.0, 0.3, 1.5]])
    ids = np.zeros(1, dtype=np.int64)
    r_geo = R.navigation(stack.geodesic(ids, p0), stack.geodesic(ids, p1), 1.0, 0.5)
    r_euc = R.navigation(np.linalg.norm(goal - p0, axis=1), np.linalg.norm(goal - p1, axis=1), 1.0, 0.5)
    assert r_geo[0] > 0.2  # ~0.3 m of progress along the geodesic
    assert r_euc[0] < 0.0


# ----------------------------------------------------------------------------- the env
@pytest.fixture(scope="module")
def quiet_env():
    return NavigationEnv(num_envs=4, **QUIET)


def test_reward_is_the_sum_of_the_logged_terms(quiet_env):
    env = quiet_env
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(30):
        _, rew, _, _, info = env.step(rng.uniform(-0.5, 0.5, (4, 4)))
        logged = sum(info["log"][f"reward/{t}"] for t in REWARD_TERMS)
        assert rew.mean() == pytest.approx(logged, abs=1e-12)


def test_collision_terminates_is_not_a_timeout_and_agrees_with_the_esdf(quiet_env):
    env = quiet_env
    # Pin env 0 just in front of the nearest obstacle of scene 0, pointing at it, at 4 m/s.
    scene = env.scenes[0]
    prim = next(p for p in scene.primitives if hasattr(p, "p0") and 10 < p.p0[0] < 50 and abs(p.p0[1]) < 10)
    target = np.array([prim.p0[0], prim.p0[1], 1.5])
    start = target - np.array([2.5, 0.0, 0.0])
    opts = {"scene_ids": [0] * 4, "start": np.tile(start, (4, 1)), "goal": np.tile([63.5, 0.0, 1.5], (4, 1)),
            "speed": [4.0] * 4, "yaw": [0.0] * 4}  # fmt: skip
    env.reset(seed=1, options=opts)
    env.vehicles.reset(np.arange(4), env.vehicles.pos_w.copy(), vel_w=np.tile([4.0, 0, 0], (4, 1)))
    hover_fwd = np.zeros((4, 4))
    for _ in range(200):
        _, rew, term, trunc, info = env.step(hover_fwd)
        if term[0]:
            break
    assert term[0] and info["collision"][0] and not trunc[0] and not info["time_outs"][0]
    assert info["log"]["episode/collision"][0] == 1.0
    # The reward of that step includes the scaled collision penalty.
    assert rew[0] <= -env.cfg.reward.scales["collision"] + 1.0
    # MuJoCo's contact and the ESDF agree: the episode's smallest ESDF at the vehicle centre (reached at the
    # contact) equals the 0.2 m collision radius up to the 0.2 m field grid's interpolation error and the
    # penetration of one 2 ms physics step at 4 m/s (8 mm).
    min_clear = info["log"]["episode/min_clearance"][0]
    assert abs(min_clear - env.cfg.vehicle.airframe.collision_radius) < 0.1


def test_out_of_bounds_ends_the_episode_with_the_collision_penalty(quiet_env):
    env = quiet_env
    opts = {"scene_ids": [0] * 4, "start": np.tile([0.5, 0.0, 1.5], (4, 1)), "goal": np.tile([63.5, 0.0, 1.5], (4, 1)),
            "speed": [4.0] * 4, "yaw": [math.pi] * 4}  # fmt: skip
    env.reset(seed=1, options=opts)
    env.vehicles.reset(np.arange(4), env.vehicles.pos_w.copy(), vel_w=np.tile([-10.0, 0, 0], (4, 1)))
    for _ in range(100):  # x < -3 m (the margin) after ~0.35 s
        _, rew, term, trunc, info = env.step(np.zeros((4, 4)))
        if term[0]:
            break
    assert term[0] and info["out_of_bounds"][0] and not info["collision"][0] and not trunc[0]
    assert rew[0] <= -env.cfg.reward.scales["collision"] + 1.0  # leaving the volume is not a free exit


def test_success_at_the_goal(quiet_env):
    env = quiet_env
    goal = np.array([63.5, 0.0, 1.5])
    opts = {"scene_ids": [1] * 4, "start": np.tile(goal - [3.0, 0, 0], (4, 1)), "goal": np.tile(goal, (4, 1)),
            "speed": [3.0] * 4}  # fmt: skip
    env.reset(seed=2, options=opts)
    _, rew, term, trunc, info = env.step(np.zeros((4, 4)))
    assert term.all() and info["success"].all() and not trunc.any()
    assert np.all(rew >= env.cfg.reward.scales["success"] - 1.0)


def test_resets_only_touch_finished_envs(quiet_env):
    env = quiet_env
    goal = np.array([63.5, 0.0, 1.5])
    starts = np.array([goal - [3.0, 0, 0], [0.5, 0, 1.5], [0.5, 3, 1.5], [0.5, -3, 1.5]])
    opts = {"scene_ids": [1] * 4, "start": starts, "goal": np.tile(goal, (4, 1)), "speed": [3.0] * 4}
    env.reset(seed=4, options=opts)
    for _ in range(5):
        env.step(np.zeros((4, 4)))
    before = env.vehicles.pos_w.copy()
    lengths = env.episode_length_buf.copy()
    # Env 0 finished on the first step (success) and was reset; envs 1-3 kept going.
    assert lengths[0] < 5 and np.all(lengths[1:] == 5)
    _, _, term, _, _ = env.step(np.zeros((4, 4)))
    assert np.all(env.episode_length_buf[1:] == 6)
    assert np.all(np.linalg.norm(env.vehicles.pos_w[1:] - before[1:], axis=1) < 0.2)


def test_domain_randomization_ranges_are_respected():
    env = NavigationEnv(num_envs=64, **SMALL)
    env.reset(seed=0)
    r = env.cfg.randomization
    mass = env.vehicles.model.body_mass[env.vehicles.body_ids]
    assert np.all(mass >= r.mass_scale.lo - 1e-12) and np.all(mass <= r.mass_scale.hi + 1e-12)
    assert mass.std() > 0.02  # actually randomised
    t_max = env.vehicles.motor_t_max / env.cfg.vehicle.max_motor_thrust
    assert np.all((t_max >= r.thrust_scale.lo - 1e-12) & (t_max <= r.thrust_scale.hi + 1e-12))
    lo, hi = r.action_latency_steps
    assert set(np.unique(env.latency_buf)) <= set(range(lo, hi + 1)) and len(np.unique(env.latency_buf)) > 1
    assert np.all(np.linalg.norm(env.wind_buf, axis=1) <= r.wind_max + 1e-12)
    gain = env.vehicles.controller.rate_p[:, 0] / env.cfg.vehicle.controller.rate_p[0]
    assert np.all((gain >= r.gain_scale.lo - 1e-12) & (gain <= r.gain_scale.hi + 1e-12))


def test_determinism_under_a_seed():
    a, b = NavigationEnv(num_envs=3, **SMALL), NavigationEnv(num_envs=3, **SMALL)
    oa, _ = a.reset(seed=11)
    ob, _ = b.reset(seed=11)
    np.testing.assert_array_equal(oa["state"], ob["state"])
    rng = np.random.default_rng(1)
    for _ in range(20):
        act = rng.uniform(-1, 1, (3, 4))
        ra, rb = a.step(act), b.step(act)
        np.testing.assert_array_equal(ra[0]["depth"], rb[0]["depth"])
        np.testing.assert_array_equal(ra[1], rb[1])


def test_batched_and_single_envs_give_the_same_transitions():
    opts1 = {"scene_ids": [0], "start": [[0.5, 1.0, 1.5]], "goal": [[63.5, 2.0, 1.5]], "speed": [5.0], "yaw": [0.1]}
    opts4 = {k: np.concatenate([np.asarray(v)] * 4) for k, v in opts1.items()}
    one, four = NavigationEnv(num_envs=1, **QUIET), NavigationEnv(num_envs=4, **QUIET)
    o1, _ = one.reset(seed=0, options=opts1)
    o4, _ = four.reset(seed=0, options=opts4)
    rng = np.random.default_rng(2)
    for _ in range(40):
        act = rng.uniform(-0.5, 0.5, (1, 4))
        o1, r1, *_ = one.step(act)
        o4, r4, *_ = four.step(np.repeat(act, 4, axis=0))
        np.testing.assert_allclose(o4["state"][0], o1["state"][0], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(r4[0], r1[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(o4["depth"][0], o1["depth"][0], atol=1e-5)


def test_observation_layout_and_spaces():
    env = NavigationEnv(num_envs=2, **SMALL)
    obs, info = env.reset(seed=0)
    assert obs["depth"].shape == (2, 1, 60, 100) and obs["depth"].dtype == np.float32
    assert obs["state"].shape == (2, STATE_DIM)
    assert env.observation_space.contains(obs)
    assert info["critic"].shape == (2, env.critic_dim)
    # Rotation block is a rotation matrix; prev action zero at reset; goal altitude inside the band.
    rot = obs["state"][:, 3:12].reshape(2, 3, 3)
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.tile(np.eye(3), (2, 1, 1)), atol=0.05)
    np.testing.assert_array_equal(obs["state"][:, 12:16], 0.0)


def test_bad_input_fails_with_the_key_or_index():
    with pytest.raises(ConfigError, match=r"reward\.nav_lambdaa"):
        NavigationEnv(num_envs=2, **{"reward.nav_lambdaa": 1.0})
    with pytest.raises(ConfigError, match=r"reward\.navigation"):
        NavigationEnv(num_envs=2, **{"reward.navigation": "manhattan"})
    with pytest.raises(ConfigError, match=r"reward\.scales\.speedy"):
        NavigationEnv(num_envs=2, **{"reward.scales": {"speedy": 1.0}})
    env = NavigationEnv(num_envs=3, **SMALL)
    env.reset(seed=0)
    act = np.zeros((3, 4))
    act[1, 2] = np.inf
    with pytest.raises(ValueError, match=r"env index\(es\) \[1\]"):
        env.step(act)


# ----------------------------------------------------------------------------- gymnasium and rsl-rl
# The state vector (velocities, the goal's offset) is unbounded by design, which the checker notes as a warning.
@pytest.mark.filterwarnings("ignore:.*A Box observation space (maximum|minimum) value is -?infinity")
def test_gymnasium_make_and_check_env():
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make("ShieldNav-v0", **SMALL)
    check_env(env.unwrapped, skip_render_check=True)
    vec = gymnasium.make_vec("ShieldNav-v0", num_envs=3, **SMALL)
    assert vec.num_envs == 3
    obs, _ = vec.reset(seed=0)
    assert obs["depth"].shape == (3, 1, 60, 100)


def test_rsl_rl_adapter_and_one_ppo_iteration(tmp_path):
    from rsl_rl.runners import OnPolicyRunner

    vec = RslRlVecEnv(NavigationEnv(num_envs=4, **SMALL))
    obs = vec.get_observations()
    assert set(obs.keys()) == {"depth", "state", "critic"}
    assert obs["depth"].shape == (4, 1, 60, 100) and obs["state"].shape == (4, STATE_DIM)
    obs, rew, done, extras = vec.step(torch.zeros(4, 4))
    assert rew.shape == (4,) and done.shape == (4,) and extras["time_outs"].shape == (4,)
    assert "reward/navigation" in extras["log"]
    cfg = {
        "num_steps_per_env": 4, "save_interval": 10, "obs_groups": {"actor": ["state"], "critic": ["critic"]},
        "algorithm": {"class_name": "PPO", "num_learning_epochs": 1, "num_mini_batches": 1},
        "actor": {"class_name": "MLPModel", "hidden_dims": [16], "activation": "elu",
                  "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": 0.5}},
        "critic": {"class_name": "MLPModel", "hidden_dims": [16], "activation": "elu"},
    }  # fmt: skip
    runner = OnPolicyRunner(vec, cfg, log_dir=str(tmp_path), device="cpu")
    runner.learn(1)
    assert list(tmp_path.glob("events.out.tfevents*"))  # rsl-rl's tensorboard writer ran
    assert math.isfinite(float(vec.get_observations()["critic"].sum()))


def test_command_path_round_trips_the_action_mapping():
    env = NavigationEnv(num_envs=3, **QUIET)
    env.reset(seed=0)
    a = np.random.default_rng(0).uniform(-1, 1, (3, 4))
    cmd = env.action_to_command(a)
    # Hand-checked mapping: action 0 -> hover g; +1 -> thrust_max; -1 -> thrust_min; tilt scales linearly.
    probe = env.action_to_command(np.array([[0.0, 0, 0, 0], [1.0, 1.0, 0, 0], [-1.0, 0, -1.0, 0]]))
    np.testing.assert_allclose(probe[:, 0], [9.81, 25.0, 2.0])
    np.testing.assert_allclose(probe[1:, 1:3], [[math.radians(45), 0], [0, -math.radians(45)]])
    np.testing.assert_allclose(env.command_to_action(cmd), a, atol=1e-12)
    env.step(a, commands=cmd)
    np.testing.assert_allclose(env.exec_action_buf, a, atol=1e-12)


def test_the_latency_line_delays_given_commands_as_it_delays_actions():
    """With a latency of 2 steps the command flown at step t is the one given at t - 2 (the hover command at the start
    heading before that), and the previous-action input is its normalised equivalent; with command_latency off, or
    without latency, the given command is flown at once."""
    lag = {**QUIET, "randomization.action_latency_steps": [2, 2]}
    env = NavigationEnv(num_envs=2, **lag)
    env.reset(seed=0)
    psi0 = env.headings.copy()
    rng = np.random.default_rng(1)
    given = [env.action_to_command(rng.uniform(-1, 1, (2, 4))) for _ in range(4)]
    flown = []
    for cmd in given:
        base = env.yaw_bases.copy()
        env.step(np.zeros((2, 4)), commands=cmd)
        flown.append(env.exec_action_buf.copy())
        if len(flown) <= 2:  # the hover command [g, 0, 0, psi0]: action 0 thrust and tilt, yaw lead psi0 - base
            lead = ((psi0 - base + np.pi) % (2 * np.pi) - np.pi) / math.radians(60.0)
            np.testing.assert_allclose(flown[-1], np.stack((np.zeros(2), np.zeros(2), np.zeros(2), lead), 1),
                                       atol=1e-12)  # fmt: skip
        else:  # the command given two steps earlier, at today's yaw base
            np.testing.assert_allclose(flown[-1], np.clip(env_cmd_to_action(env, given[len(flown) - 3], base), -1, 1))
    for extra in ({"randomization.command_latency": False}, {"randomization.action_latency_steps": [0, 0]}):
        now = NavigationEnv(num_envs=2, **{**lag, **extra})
        now.reset(seed=0)
        base = now.yaw_bases.copy()
        now.step(np.zeros((2, 4)), commands=given[0])
        np.testing.assert_allclose(now.exec_action_buf, np.clip(env_cmd_to_action(now, given[0], base), -1, 1))


def env_cmd_to_action(env, cmd, base):
    from envs.navigation import interface

    return interface.command_to_action(cmd, base, env.cfg.action, env.cfg.vehicle.gravity)


def test_velocity_yaw_base_leads_from_the_direction_of_travel():
    env = NavigationEnv(num_envs=4, **QUIET, **{"action.yaw_base": "velocity", "action.yaw_base_speed": 2.0})
    env.reset(seed=0)
    # Heading 0 for every vehicle (level, identity attitude); horizontal velocities by hand.
    pos = env.vehicles.pos_w.copy()
    vel = np.array([[0.0, 3.0, 0.0], [0.0, 1.0, 0.5], [-4.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    env.vehicles.reset(np.arange(4), pos, vel_w=vel)
    np.testing.assert_allclose(env.headings, 0.0, atol=1e-12)
    # 3 m/s along +y: base 90 deg; 1 m/s of 2: half way (45 deg), the vertical part ignored; -x: 180 deg
    # (the wrapped difference is +-pi, either sign is the same heading); at rest: the heading.
    base = env.yaw_bases
    np.testing.assert_allclose(base[[0, 1, 3]], [math.pi / 2, math.pi / 4, 0.0], atol=1e-12)
    assert abs(abs(base[2]) - math.pi) < 1e-12
    a = np.zeros((4, 4))
    a[:, 3] = 0.5  # +30 deg lead on the base
    psi = env.action_to_command(a)[:, 3]
    np.testing.assert_allclose(psi[[0, 1, 3]], np.radians([120.0, 75.0, 30.0]), atol=1e-12)
    assert abs((psi[2] - math.radians(210.0) + math.pi) % (2 * math.pi) - math.pi) < 1e-12
    # The inverse uses the same base, and the default mapping still leads from the heading.
    np.testing.assert_allclose(env.command_to_action(env.action_to_command(a)), a, atol=1e-12)
    plain = NavigationEnv(num_envs=4, **QUIET)
    plain.reset(seed=0)
    plain.vehicles.reset(np.arange(4), plain.vehicles.pos_w.copy(), vel_w=vel)
    np.testing.assert_allclose(plain.action_to_command(a)[:, 3], math.radians(30.0), atol=1e-12)
    with pytest.raises(ConfigError, match=r"action\.yaw_base"):
        NavigationEnv(num_envs=2, **SMALL, **{"action.yaw_base": "goal"})
    with pytest.raises(ConfigError, match=r"action\.yaw_base_speed"):
        NavigationEnv(num_envs=2, **SMALL, **{"action.yaw_base_speed": 0.0})


def test_teacher_local_map_is_the_esdf_on_the_heading_frame_grid():
    lm = {"local_map.enabled": True, "local_map.xs": [0.0, 2.0], "local_map.ys": [-1.0, 1.5],
          "local_map.zs": [0.0, 0.5], "local_map.clip": 3.0, "render_depth": False}  # fmt: skip
    env = NavigationEnv(num_envs=2, **QUIET, **lm)
    start = np.array([[1.0, -3.0, 1.2], [1.0, 4.0, 1.5]])
    yaw = np.array([math.pi / 2, 0.0])  # env 0 heads +y (forward x -> world +y, left y -> world -x), env 1 heads +x
    _, info = env.reset(seed=0, options={"scene_ids": np.array([0, 1]), "start": start, "yaw": yaw})
    teacher = info["teacher"]
    assert teacher.shape == (2, STATE_DIM + 8) == (2, env.teacher_dim)
    np.testing.assert_allclose(teacher[:, :STATE_DIM], info["critic"][:, :STATE_DIM], atol=1e-6)  # clean state
    # Grid order: xs outermost, then ys, then zs (meshgrid "ij"); world offsets written out by hand.
    offsets = [(x, y, z) for x in (0.0, 2.0) for y in (-1.0, 1.5) for z in (0.0, 0.5)]
    pts0 = np.array([[1.0 - y, -3.0 + x, 1.2 + z] for x, y, z in offsets])
    pts1 = np.array([[1.0 + x, 4.0 + y, 1.5 + z] for x, y, z in offsets])
    pos = env.local_pos
    np.testing.assert_allclose(pos, start, atol=1e-9)
    for k, pts in enumerate((pts0, pts1)):
        want = np.clip(env.field_stack.esdf(np.full(8, k), pts), -3.0, 3.0) / 3.0
        np.testing.assert_allclose(teacher[k, STATE_DIM:], want, atol=1e-6)
    # Nothing is rendered: the depth group is all zeros, also after a step.
    obs, *_, info = env.step(np.zeros((2, 4)))
    assert not obs["depth"].any() and info["teacher"].shape == (2, env.teacher_dim)
    # Without the map there is no teacher group.
    _, info = NavigationEnv(num_envs=2, **SMALL).reset(seed=0)
    assert "teacher" not in info


@pytest.mark.parametrize("family", ["train", "train_shapes"])
def test_rsl_rl_adapter_restores_curriculum_levels(family):
    vec = RslRlVecEnv(NavigationEnv(num_envs=4, **{"scenes.family": family, "scenes.indices": [0, 1, 2]}))
    vec.set_curriculum_levels([2, 0, 1, 2])
    assert vec.curriculum_levels == [2, 0, 1, 2]
    np.testing.assert_array_equal(vec.env.scene_id_buf, [2, 0, 1, 2])  # every episode restarted on its level
    with pytest.raises(ValueError, match="curriculum levels"):
        vec.set_curriculum_levels([0, 3, 0, 0])


def test_circling_is_the_net_heading_rotation_over_ten_seconds(quiet_env, monkeypatch):
    # The bookkeeping behind episode/circling on scripted headings: env 0 orbits at 1 rad/s (crossing the +-pi seam
    # every 6.3 s), env 1 weaves +-0.5 rad, env 2 turns half a turn and back, env 3 is frozen while it would orbit.
    env = quiet_env
    env.reset(seed=0)
    dt = env.cfg.vehicle.command_dt
    script = {"h": np.zeros(4)}
    monkeypatch.setattr(NavigationEnv, "headings", property(lambda self: script["h"].copy()))
    env.heading_prev_buf[:] = 0.0
    env.heading_total_buf[:] = 0.0
    env.heading_hist_buf[:] = 0.0
    env.ep_max_turns_buf[:] = 0.0
    live = np.array([True, True, True, False])
    for k in range(1, 1501):  # 15 s
        t = k * dt
        turn = math.pi * min(t, 5.0) / 5.0 - math.pi * max(0.0, min(t - 5.0, 5.0)) / 5.0
        h = np.array([t, 0.5 * math.sin(t), turn, t])
        script["h"] = (h + math.pi) % (2 * math.pi) - math.pi
        env.episode_length_buf[:] = k
        env._track_turns(live)
    # Orbit: 10 rad in every 10 s window -> 10 / 2 pi = 1.59 turns (>= 1.5: circling).
    assert env.ep_max_turns_buf[0] == pytest.approx(10.0 / (2 * math.pi), abs=1e-9)
    # Weave: at most 1 rad apart (0.16 turns); half a turn and back: 0.5 turns; the frozen env counted nothing.
    assert env.ep_max_turns_buf[1] <= 1.0 / (2 * math.pi) + 1e-9
    assert env.ep_max_turns_buf[2] == pytest.approx(0.5, abs=1e-9)
    assert env.ep_max_turns_buf[3] == 0.0
