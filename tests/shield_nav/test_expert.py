"""Oracle DAgger: the scripted expert's labels, the ``expert`` observation group, the ``ExpertTeacher`` model and the
config checks, against independent computations on the real task (2 training scenes)."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from envs.config import ConfigError
from envs.navigation import NavigationEnv
from envs.rsl_rl import RslRlVecEnv
from shield_nav.algorithms.baselines import (
    BaselineConfig,
    EuclideanOracleController,
    GoalSeeker,
    OracleConfig,
    OracleController,
    OracleExpert,
    make_baseline,
)
from shield_nav.policies.models import ExpertTeacher
from shield_nav.training import load_train_config, make_env, make_runner

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SMALL = {"scenes.indices": [0, 1], "episode.initial_speed_fraction": [0.3, 0.5]}


def test_expert_action_maps_back_to_the_oracle_command():
    """The label is the oracle's command in action space: action_to_command(label) == the command (unclipped)."""
    env = NavigationEnv(num_envs=16, **SMALL)
    env.reset(seed=4)
    cfg = BaselineConfig(oracle=OracleConfig(episode_goal=True))
    expert, oracle = OracleExpert(cfg), OracleController(cfg)
    for _ in range(30):  # fly the expert a little, so the states are not all at the start
        env.step(expert(env))
    cmd = oracle.commands(env)
    act = expert(env)
    assert act.shape == (16, 4) and np.all(np.abs(act) <= 1.0)
    inside = np.all(np.abs(act) < 0.999, axis=1)
    assert inside.sum() >= 8  # most commands lie inside the action range
    back = env.action_to_command(act)
    np.testing.assert_allclose(back[inside, :3], cmd[inside, :3], atol=1e-9)
    yaw_err = (back[inside, 3] - cmd[inside, 3] + math.pi) % (2 * math.pi) - math.pi
    np.testing.assert_allclose(yaw_err, 0.0, atol=1e-9)


def test_episode_goal_field_is_the_anchor_field():
    """With ``episode_goal`` the oracle descends the episode's anchor field, else the goal region's field."""
    env = NavigationEnv(num_envs=8, **SMALL)
    env.reset(seed=2)
    pts = env.local_pos
    ep = OracleController(BaselineConfig(oracle=OracleConfig(episode_goal=True)))
    reg = OracleController(BaselineConfig())
    want_ep = env.anchor_fields.geodesic(env.scene_id_buf, env.anchor_buf, pts)
    want_reg = env.field_stack.geodesic(env.scene_id_buf, pts)
    np.testing.assert_allclose(ep._geodesic(env, env.scene_id_buf, pts, 1), want_ep)
    np.testing.assert_allclose(reg._geodesic(env, env.scene_id_buf, pts, 1), want_reg)
    assert not np.allclose(want_ep, want_reg)  # a goal point is farther than the nearest point of the goal box


def test_inflated_expert_fields_are_built_with_their_radius():
    """``field_radius`` > 0: the oracle descends fields built with that inflation (independently rebuilt here)."""
    from envs.fields import FieldStack, build_fields

    env = NavigationEnv(num_envs=8, **SMALL)
    env.reset(seed=2)
    oracle = OracleController(BaselineConfig(oracle=OracleConfig(field_radius=0.5)))
    stack = FieldStack([build_fields(s, resolution=env.cfg.scenes.field_resolution, vehicle_radius=0.5)
                        for s in env.scenes])  # fmt: skip
    rng = np.random.default_rng(0)
    lo, hi = env.scenes[0].bounds_lo, env.scenes[0].bounds_hi
    pts = rng.uniform(lo, hi, (64, 3))
    ids = np.zeros(64, dtype=np.int64)
    got = oracle._geodesic(env, ids, pts, 1)
    np.testing.assert_allclose(got, stack.geodesic(ids, pts))
    assert not np.allclose(got, env.field_stack.geodesic(ids, pts))  # the 0.2 m field differs near obstacles
    assert oracle._fields(env)[0] is oracle._fields(env)[0]  # built once per env


def test_euclidean_guidance_is_goal_seeking_away_from_obstacles():
    """``guidance: euclidean`` flies straight at the goal point: where neither the repulsion nor the slow-down acts
    (ESDF above both thresholds) its command is exactly the goal seeker's; the geodesic oracle's is not."""
    env = NavigationEnv(num_envs=32, **SMALL)
    env.reset(seed=5)
    cfg = BaselineConfig(oracle=OracleConfig(lookahead_s=0.0))  # read the direction at p, as the goal seeker does
    euclid = make_baseline("oracle_euclidean", cfg)
    assert isinstance(euclid, EuclideanOracleController) and euclid.cfg.oracle.guidance == "euclidean"
    assert cfg.oracle.guidance == "geodesic"  # the row's controller does not alter the shared config
    d = env.field_stack.esdf(env.scene_id_buf, env.local_pos)
    far_from_goal = np.linalg.norm(env.goal_buf - env.local_pos, axis=1) > cfg.oracle.goal_switch
    free = (d > max(cfg.oracle.repulse_dist, cfg.oracle.slow_dist)) & far_from_goal
    assert free.sum() >= 16
    got, want = euclid.commands(env), GoalSeeker(cfg).commands(env)
    np.testing.assert_allclose(got[free], want[free], atol=1e-9)
    geo = OracleController(cfg).commands(env)
    assert np.abs(geo[free] - want[free]).max() > 1e-3  # the geodesic descent is not the straight line


def test_the_camera_map_experts_field_is_the_path_length_round_what_its_camera_mapped():
    """``expert_cammap``'s Phi on a 20 x 10 m map of 0.2 m cells, goal (18, 5.1), goal disc 2 m. Empty map: at the
    cell centre (2.1, 5.1) Phi is the distance to the disc's nearest cell centre, 16.1 - 2.1 = 14.0 m. A mapped wall at
    x = 10 for y < 8 (inflated 0.5 m): the way passes above y = 8.5 at x = 10.1, so Phi >= hypot(8, 3.4) +
    hypot(7.9, 3.4) - 2 = 15.3 m, and the way through (10.1, 9.2) bounds it by hypot(8, 4.1) + hypot(7.9, 4.1) - 2 =
    15.9 m (+ the grid stencil's error)."""
    from envs.camera.config import CameraConfig
    from shield_nav.safety.camera_map import CameraMap

    planner = make_baseline("expert_cammap", BaselineConfig())
    assert planner.reads_depth and planner.privileged
    planner._map = CameraMap(planner.ec.camera_map, 1, CameraConfig(), np.zeros(2), np.array([20.0, 10.0]))
    goal = np.array([18.0, 5.1, 1.5])
    assert planner.phi_map(0, goal)[10, 25] == pytest.approx(14.0, abs=0.1)
    planner._map.grid[0, 50, :40] = True
    phi = planner.phi_map(0, goal)[10, 25]
    assert (
        math.hypot(8, 3.4) + math.hypot(7.9, 3.4) - 2 - 0.05
        <= phi
        <= math.hypot(8, 4.1) + math.hypot(7.9, 4.1) - 2 + 0.3
    )


def test_the_camera_map_experts_narrow_field_keeps_to_a_corridor_its_inflated_map_closes():
    """The camera-map expert's corridor mode on a 20 x 10 m map of 0.2 m cells: a wall at x = 10.1 m closes the map
    but for a corridor along y between mapped rows at y = 4.5 and 5.5 m (x 6.1-14.1 m). Its interior cells lie 0.2 or
    0.4 m from a wall, so the 0.5 m inflation closes it: the inflated field is flat (unreachable) at (2.1, 5.1). The
    narrow field passes the cells more than the vehicle radius (0.2 m) from the walls (y = 4.9 and 5.1), each metre
    there weighed 1 + 4 (0.6 - 0.4) / 0.6 = 7/3, so 4 m along the corridor's middle add 28/3 m; the cells next to the
    walls (0.2 m) are not traversable, so the field climbs towards them. A vehicle 0.4 m from a mapped wall takes the
    narrow field, one 3 m from everything mapped the expert's test."""
    from types import SimpleNamespace

    from envs.camera.config import CameraConfig
    from shield_nav.safety.camera_map import CameraMap

    planner = make_baseline("expert_cammap", BaselineConfig())
    ec = planner.ec
    assert (ec.narrow_clearance, ec.narrow_weight, ec.camera_map.map_inflate) == (0.6, 4.0, 0.5)
    cmap = CameraMap(ec.camera_map, 2, CameraConfig(), np.zeros(2), np.array([20.0, 10.0]))
    grid = cmap.grid[0]
    grid[50, :] = True
    grid[30:71, 22] = grid[30:71, 27] = True
    grid[50, 23:27] = False  # the corridor's way through the wall
    goal = np.array([18.0, 5.0, 1.5])
    planner._map = cmap
    phi = planner.phi_map(0, goal)
    assert phi[10, 25] == phi[10, 5] == phi.max()  # closed: the unreachable value, flat round the vehicle
    q = cmap.narrow_field(0, goal, 0.2, ec.narrow_clearance, ec.narrow_weight)
    assert q[40, 25] - q[60, 25] == pytest.approx(4.0 * 7.0 / 3.0, abs=1e-3)
    assert q[40, 24] == pytest.approx(q[40, 25], abs=1e-3)  # both 0.4 m from a wall
    assert q[40, 23] > q[40, 24] + 0.1  # 0.2 m from the wall: not traversable, filled from its neighbour
    assert q[10, 25] < phi.max()  # the narrow field has a way where the inflated one has none
    free = cmap.narrow_field(1, goal, 0.2, ec.narrow_clearance, ec.narrow_weight)  # nothing mapped: metres
    assert free[10, 25] == pytest.approx(16.1 - 2.1, abs=0.1)
    planner._narrow = True
    planner._clear = np.stack([cmap.clearance(0), cmap.clearance(0)]).astype(np.float32)
    env = SimpleNamespace(local_pos=np.array([[8.1, 4.9, 1.5], [2.1, 2.1, 1.5]]), num_envs=2)
    np.testing.assert_array_equal(planner._closed(env, np.array([1.0, 1.0])), [True, False])
    np.testing.assert_array_equal(planner._closed(env, np.array([1.0, 0.0])), [True, True])  # flat: the expert's


def test_the_camera_map_expert_descends_each_flights_own_field_and_needs_the_image():
    """In a real env, after one command: the field the path descends, read at cell centres through the kernel's
    lookup (rows = flights), is each flight's own map field plus the height difference to its goal; a non-rendering
    env is refused by name."""
    env = NavigationEnv(num_envs=4, **SMALL)
    env.reset(seed=3)
    planner = make_baseline("expert_cammap", BaselineConfig())
    cmd = planner.commands(env)
    assert cmd.shape == (4, 4) and np.isfinite(cmd).all()
    assert planner._map.grid.any()
    lo, res = planner._map.lo, planner.ec.camera_map.map_cell
    rows = np.arange(4)
    for a, b in ((10, 30), (60, 80), (150, 20)):
        for z in planner._origin[0, 2] + res * np.array([2, 7, 12]):  # layer heights: no interpolation across
            pts = np.tile([lo[0] + (a + 0.5) * res, lo[1] + (b + 0.5) * res, z], (4, 1))
            got = planner._phi(env, env.scene_id_buf, env.anchor_buf, pts, rows=rows)
            want = [planner.phi_map(i, env.goal_buf[i])[a, b] + abs(z - env.goal_buf[i, 2]) for i in range(4)]
            np.testing.assert_allclose(got, want, rtol=1e-6)
            got = planner._phi(env, env.scene_id_buf, env.anchor_buf, pts, own=False, rows=rows)  # the narrow field
            want = [planner._map.narrow_field(i, env.goal_buf[i], planner._radius, planner.ec.narrow_clearance,
                                              planner.ec.narrow_weight)[a, b] + abs(z - env.goal_buf[i, 2])
                    for i in range(4)]  # fmt: skip
            np.testing.assert_allclose(got, want, rtol=1e-6)
    blind = NavigationEnv(num_envs=2, render_depth=False, **SMALL)
    blind.reset(seed=3)
    with pytest.raises(ValueError, match="render_depth"):
        make_baseline("expert_cammap", BaselineConfig()).commands(blind)


def test_the_map_planner_plans_only_the_flights_it_is_given_and_a_new_one_at_once():
    """``commands(env, among)``: at a replan step only the flights in ``among`` get a plan (a primitive, a map target);
    a flight added between replan steps is planned at that call; every flight's image is mapped all along."""
    from shield_nav.safety.camera_map import CameraMap

    env = NavigationEnv(num_envs=3, **SMALL)
    env.reset(seed=3)
    planner = make_baseline("reactive_map", BaselineConfig())
    planner.commands(env, among=np.array([True, False, False]))  # step 0: a replan and map step
    assert np.abs(planner._v_des[0]).sum() > 0 and not planner._v_des[1:].any()
    assert planner._planned.tolist() == [True, False, False]
    ref = CameraMap.for_env(planner.cfg.reactive.camera_map, env)  # all three images mapped, as a map of its own
    ref.observe(np.arange(3), env.local_pos, env.vehicles.R_wb, env.sensor_depth_buf, float(env.scenes[0].bounds_lo[2]))
    np.testing.assert_array_equal(planner._map.map.grid, ref.grid)
    assert ref.grid.any()
    assert np.isfinite(planner._map.target[0]).all() and np.isnan(planner._map.target[1:]).all()
    v0 = planner._v_des[0].copy()
    env.step(np.zeros((3, 4)))
    planner.commands(env, among=np.array([True, True, False]))  # step 1: no replan, but flight 1 is new
    assert np.abs(planner._v_des[1]).sum() > 0 and not planner._v_des[2].any()
    np.testing.assert_array_equal(planner._v_des[0], v0)  # flight 0 keeps its plan until the next replan step
    assert np.isfinite(planner._map.target[1]).all() and np.isnan(planner._map.target[2]).all()


def test_reactive_planner_aligns_with_its_guidance():
    """With only the alignment term in the score, the reactive planner picks the primitive closest to its guide:
    the goal direction (``euclidean``), -grad Phi at the vehicle (``geodesic``, Phi differenced here by hand) or the
    direction to the point its camera map's plan gives (``map``, not privileged)."""
    env = NavigationEnv(num_envs=12, **SMALL)
    env.reset(seed=3)
    for _ in range(20):
        env.step(np.zeros((12, 4)))
    pos, ids = env.local_pos, env.scene_id_buf
    h = 0.2
    grad = np.stack([(env.field_stack.geodesic(ids, pos + h * e) - env.field_stack.geodesic(ids, pos - h * e)) / (2 * h)
                     for e in np.eye(3)], axis=1)  # fmt: skip
    far = env.field_stack.geodesic(ids, pos) > 3.0  # outside the oracle's goal switch
    assert far.all()
    guides = {"euclidean": env.goal_buf - pos, "geodesic": -grad, "map": None}
    chosen = {}
    for kind, guide in guides.items():
        cfg = BaselineConfig()
        cfg.reactive.w_free = cfg.reactive.w_smooth = cfg.reactive.min_free = 0.0
        planner = make_baseline({"euclidean": "reactive"}.get(kind, f"reactive_{kind}"), cfg)
        assert planner.privileged == (kind == "geodesic")
        planner.reset(env)
        planner.commands(env)
        if kind == "map":  # towards its plan's point at the goal's height, or at the goal where the plan reaches it
            target = planner._map.target
            aim = np.isfinite(target[:, 0])
            guide = env.goal_buf - pos
            guide[aim, :2] = target[aim] - pos[aim, :2]
            assert planner._map.map.grid.any()  # the first images mapped something
        psi0 = np.arctan2(env.vehicles.R_wb[:, 1, 0], env.vehicles.R_wb[:, 0, 0])
        a = psi0[:, None] + planner._az[None]
        el = np.broadcast_to(planner._el, a.shape)
        dirs = np.stack((np.cos(a) * np.cos(el), np.sin(a) * np.cos(el), np.sin(el)), axis=2)  # (N, K, 3)
        want = dirs[np.arange(12), np.argmax(np.einsum("nkj,nj->nk", dirs, guide), axis=1)]
        np.testing.assert_allclose(planner._dir, want, atol=1e-12)
        chosen[kind] = planner._dir.copy()
    assert np.abs(chosen["euclidean"] - chosen["geodesic"]).max() > 0.05  # the two guides pick differently


def test_unknown_oracle_guidance_fails_by_name():
    path = os.path.join(REPO, "configs", "experiments", "kickstart_3ms.yaml")
    with pytest.raises(ConfigError, match=r"runner.expert.params.oracle.guidance.*'manhattan'"):
        load_train_config(path, overrides=["runner.expert.params.oracle.guidance=manhattan"])
    cfg = load_train_config(path, overrides=["runner.expert.params.oracle.guidance=euclidean"])
    expert = OracleExpert(cfg.runner.expert.params)
    assert expert.controller.cfg.oracle.guidance == "euclidean"


def test_the_camera_map_expert_forgets_a_restarted_envs_map_and_plans_it_on_its_first_image():
    """``planner_cammap`` as a DAgger expert: after steps that mapped every env, env 1 restarts on its own; at the next
    label its map is exactly its new first image's cells (an independent map of that image alone), the other envs
    keep theirs, and the field its label descends is the one over that map (read through the kernel's lookup)."""
    from shield_nav.algorithms.baselines import EXPERTS
    from shield_nav.safety.camera_map import CameraMap

    env = NavigationEnv(num_envs=3, **SMALL)
    env.reset(seed=3)
    expert = EXPERTS["planner_cammap"](BaselineConfig())
    for _ in range(6):  # steps 0 and 5 map every image
        act = expert(env)
        assert act.shape == (3, 4) and np.isfinite(act).all() and np.abs(act).max() <= 1.0
        env.step(act)
    planner = expert.controller
    kept = planner._map.grid[[0, 2]].copy()
    assert planner._map.grid[1].any()
    env.reset(options={"env_ids": np.array([1])})
    assert env.episode_length_buf.tolist()[1] == 0 and min(env.episode_length_buf[[0, 2]]) > 0
    act = expert(env)  # step 6: no mapping step, but env 1 is new
    assert np.isfinite(act).all()
    ref = CameraMap.for_env(planner.ec.camera_map, env)
    ref.observe(
        np.array([1]), env.local_pos, env.vehicles.R_wb, env.sensor_depth_buf, float(env.scenes[0].bounds_lo[2])
    )
    assert ref.grid[1].any()
    np.testing.assert_array_equal(planner._map.grid[1], ref.grid[1])
    np.testing.assert_array_equal(planner._map.grid[[0, 2]], kept)
    want_field = ref.field(1, env.goal_buf[1], covered_goal="keep")[0]
    res, lo = planner.ec.camera_map.map_cell, planner._map.lo
    for a, b in ((10, 30), (60, 80), (150, 20)):
        z = planner._origin[0, 2] + 7 * res
        pts = np.array([[lo[0] + (a + 0.5) * res, lo[1] + (b + 0.5) * res, z]])
        got = planner._phi(env, env.scene_id_buf[[1]], env.anchor_buf[[1]], pts, rows=np.array([1]))
        np.testing.assert_allclose(got, [want_field[a, b] + abs(z - env.goal_buf[1, 2])], rtol=1e-6)


def test_expert_group_follows_resets_and_steps():
    expert = OracleExpert()
    vec = RslRlVecEnv(NavigationEnv(num_envs=4, **SMALL), expert=expert)
    np.testing.assert_allclose(vec.get_observations()["expert"].numpy(), expert(vec.env), atol=1e-6)
    for _ in range(5):
        obs, _, _, _ = vec.step(torch.zeros(4, 4))
        assert obs["expert"].dtype == torch.float32
        np.testing.assert_allclose(obs["expert"].numpy(), expert(vec.env), atol=1e-6)


def test_expert_flown_share_flies_the_drawn_episodes_on_the_labels():
    """DAgger's mixing: an env drawn for the expert flies its labels whatever action it is given, the others fly the
    given action; checked step for step against a twin env flown by hand, and each ended episode is drawn anew from
    the adapter's own stream (the env's draws unchanged)."""
    expert = OracleExpert()
    vec = RslRlVecEnv(NavigationEnv(num_envs=6, **SMALL), expert=expert, expert_flown_share=0.5)
    twin = NavigationEnv(num_envs=6, **SMALL)
    twin.reset(seed=twin.cfg.seed)
    rng = np.random.default_rng([twin.cfg.seed, 0xBE7A])
    drawn = rng.random(6) < 0.5
    assert 0 < drawn.sum() < 6  # this seed draws both kinds
    np.testing.assert_array_equal(vec.expert_flown, drawn)
    given = np.tile([[0.2, 0.1, -0.1, 0.0]], (6, 1))
    for _ in range(8):
        act = np.where(drawn[:, None], expert(twin), given)
        twin.step(act)
        vec.step(torch.as_tensor(given, dtype=torch.float32))
        np.testing.assert_allclose(vec.env.local_pos, twin.local_pos, atol=1e-9)
    assert np.abs(vec.env.local_pos[drawn] - vec.env.local_pos[~drawn].mean(0)).min() > 1e-3
    vec.episode_length_buf = torch.as_tensor(vec.env.max_episode_length_buf - 1)  # every episode times out next step
    _, _, dones, _ = vec.step(torch.as_tensor(given, dtype=torch.float32))
    assert dones.all()
    np.testing.assert_array_equal(vec.expert_flown, rng.random(6) < 0.5)
    with pytest.raises(ValueError, match="expert_flown_share must be in"):
        RslRlVecEnv(NavigationEnv(num_envs=2, **SMALL), expert=expert, expert_flown_share=1.5)
    with pytest.raises(ValueError, match="needs an expert"):
        RslRlVecEnv(NavigationEnv(num_envs=2, **SMALL), expert_flown_share=0.5)


def test_expert_teacher_passes_the_group_through_and_checks_shapes():
    obs = TensorDict({"expert": torch.randn(3, 4), "state": torch.randn(3, 21)}, batch_size=[3])
    model = ExpertTeacher(obs, {"teacher": ["expert"]}, "teacher", 4)
    assert list(model.parameters()) == [] and model.get_hidden_state() is None
    torch.testing.assert_close(model(obs), obs["expert"])
    with pytest.raises(ValueError, match="exactly one observation group"):
        ExpertTeacher(obs, {"teacher": ["expert", "state"]}, "teacher", 4)
    with pytest.raises(ValueError, match="group 'state' has shape"):
        ExpertTeacher(obs, {"teacher": ["state"]}, "teacher", 4)


def test_distillation_runner_labels_with_the_oracle():
    """rsl-rl's Distillation stores the oracle's action of each visited state as the privileged action."""
    cfg = load_train_config(
        os.path.join(REPO, "configs", "experiments", "distill_oracle.yaml"),
        overrides=["env.num_envs=4", "env.scenes.indices=[0,1]", "runner.num_steps_per_env=4"],
    )
    env = make_env(cfg)
    runner = make_runner(env, cfg, log_dir=None, device="cpu")
    reference = OracleExpert(cfg.runner.expert.params)
    obs = env.get_observations()
    for _ in range(3):
        want = reference(env.env)
        runner.alg.act(obs)
        np.testing.assert_allclose(runner.alg.transition.privileged_actions.numpy(), want, atol=1e-6)
        obs, rew, dones, extras = env.step(runner.alg.transition.actions)
        runner.alg.process_env_step(obs, rew, dones, extras)


def test_expert_config_errors_name_the_key():
    path = os.path.join(REPO, "configs", "experiments", "distill_oracle.yaml")
    with pytest.raises(ConfigError, match="runner.expert.kind"):
        load_train_config(path, overrides=["runner.expert.kind=mpc"])
    with pytest.raises(ConfigError, match="runner.expert.kind"):
        load_train_config(path, overrides=["runner.expert.kind="])  # the 'expert' group needs an expert
    with pytest.raises(ConfigError, match="runner.teacher.class_name"):
        load_train_config(path, overrides=["runner.teacher.class_name=MLPModel"])
    quick = os.path.join(REPO, "configs", "train", "quick.yaml")
    with pytest.raises(ConfigError, match="only with runner.class_name DistillationRunner"):
        load_train_config(quick, overrides=["runner.expert.kind=oracle"])
    with pytest.raises(ConfigError, match=r"runner.expert.flown_share.*must be in \[0, 1\], got 1.5"):
        load_train_config(path, overrides=["runner.expert.flown_share=1.5"])
    with pytest.raises(ConfigError, match=r"runner.expert.flown_share.*only with runner.class_name Distillation"):
        load_train_config(quick, overrides=["runner.expert.flown_share=0.5"])
    assert load_train_config(path, overrides=["runner.expert.flown_share=0.5"]).runner.expert.flown_share == 0.5


def run_train(*args):
    return subprocess.run([sys.executable, "train.py", *args], cwd=REPO, capture_output=True, text=True, timeout=240)


def test_train_cli_distills_from_the_oracle_then_fine_tunes_with_ppo(tmp_path):
    """train.py runs oracle DAgger end to end (no teacher checkpoint, a deployable export), then PPO fine-tunes that
    student: the actor starts as the student, stays frozen through the critic warm-up, then trains."""
    root = str(tmp_path / "logs")
    small = ["--num-envs", "4", "--log-dir", root, "--set", "runner.num_steps_per_env=8", "env.scenes.indices=[0,1]"]
    res = run_train("--config", "configs/experiments/distill_oracle.yaml", "--max-iterations", "1", *small)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "teacher: the scripted 'oracle' expert" in res.stdout
    (run,) = os.listdir(os.path.join(root, "shield_nav"))
    run_dir = os.path.join(root, "shield_nav", run)
    student_path = os.path.join(run_dir, "model_0.pt")
    ckpt = torch.load(student_path, weights_only=False)
    assert ckpt["teacher_state_dict"] == {} and ckpt["infos"]["config"]["runner"]["expert"]["kind"] == "oracle"
    assert os.path.isfile(os.path.join(run_dir, "exported", "policy.onnx"))
    res = run_train("--resume", student_path, "--max-iterations", "2")  # no teacher weights to restore
    assert res.returncode == 0, res.stderr[-3000:]
    assert "continuing at iteration 1" in res.stdout and os.path.isfile(os.path.join(run_dir, "model_1.pt"))

    res = run_train("--config", "configs/experiments/finetune_dijkstra_cbf.yaml", "--max-iterations", "2", *small,
                    f"runner.actor_init={student_path}", "runner.critic_warmup_iterations=1",
                    "runner.save_interval=1", "runner.algorithm.num_mini_batches=2")  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "actor initialised from" in res.stdout and "critic warm-up done" in res.stdout
    (ft,) = [d for d in os.listdir(os.path.join(root, "shield_nav")) if d.endswith("_finetuned")]
    ft_dir = os.path.join(root, "shield_nav", ft)
    after_warmup = torch.load(os.path.join(ft_dir, "model_0.pt"), weights_only=False)["actor_state_dict"]
    after_ppo = torch.load(os.path.join(ft_dir, "model_1.pt"), weights_only=False)["actor_state_dict"]
    assert after_warmup.keys() == ckpt["student_state_dict"].keys()
    for k, v in ckpt["student_state_dict"].items():
        if "normalizer" not in k:  # running statistics keep updating while the weights are frozen
            torch.testing.assert_close(after_warmup[k], v)
    moved = [k for k in after_ppo if "normalizer" not in k and not torch.equal(after_ppo[k], after_warmup[k])]
    assert moved  # the actor trains once the warm-up is over


def test_fine_tune_inputs_fail_fast(tmp_path):
    root = str(tmp_path / "logs")
    res = run_train("--config", "configs/experiments/finetune_dijkstra_cbf.yaml", "--log-dir", root,
                    "--set", "runner.actor_init=nowhere/model.pt")  # fmt: skip
    assert res.returncode == 2 and "runner.actor_init" in res.stderr and "nowhere/model.pt" in res.stderr
    res = run_train("--config", "configs/experiments/finetune_dijkstra_cbf.yaml", "--log-dir", root,
                    "--set", "runner.algorithm.schedule=adaptive")  # fmt: skip
    assert res.returncode == 2 and "runner.critic_warmup_iterations" in res.stderr
    res = run_train("--config", "configs/experiments/distill_oracle.yaml", "--log-dir", root,
                    "--set", "runner.actor_init=checkpoints/dijkstra_cbf/model.pt")  # fmt: skip
    assert res.returncode == 2 and "runner.actor_init" in res.stderr and "OnPolicyRunner" in res.stderr
    assert not os.path.exists(root)  # nothing was started


def test_a_run_notes_the_expert_settings_its_initial_policy_did_not_learn_from(capsys):
    """A fine-tune that switches the expert's tracker says so: the shipped student's stored config (the `tangent`
    tracker) against its own recipe gives no line, against the recipe with the `mppi` tracker exactly that change."""
    from envs.config import to_dict
    from shield_nav.training.runner import _note_expert_switch, expert_changes

    before = {"kind": "planner", "flown_share": 0.0, "params": {"expert": {"tracker": "tangent", "max_tilt_deg": 48.0}}}
    after = {"kind": "planner", "flown_share": 0.5, "params": {"expert": {"tracker": "mppi", "max_tilt_deg": 48.0},
                                                             "oracle": {"field_radius": 0.5}}}  # fmt: skip
    assert expert_changes(before, after) == ["params.expert.tracker: 'tangent' -> 'mppi'"]  # mixing, new keys: none
    assert expert_changes({**before, "kind": "oracle"}, before) == ["kind: 'oracle' -> 'planner'"]
    assert expert_changes({"kind": "", "params": {}}, after) == [] and expert_changes(None, after) == []

    path = "checkpoints/student/model.pt"
    infos = torch.load(path, map_location="cpu", weights_only=False)["infos"]
    same = load_train_config("configs/train/recipe_student.yaml")
    assert expert_changes(infos["config"]["runner"]["expert"], to_dict(same.runner.expert)) == []
    _note_expert_switch(same, path, infos, "runner.student_init")
    assert capsys.readouterr().out == ""
    switched = load_train_config("configs/train/recipe_student.yaml", ["runner.expert.params.expert.tracker=mppi"])
    _note_expert_switch(switched, path, infos, "runner.student_init")
    out = capsys.readouterr().out
    assert "runner.student_init" in out and path in out and out.count("->") == 1
    assert "params.expert.tracker: 'tangent' -> 'mppi'" in out
