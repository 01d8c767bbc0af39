"""The deployment loop (`shield_nav.deploy`): the policy's interface by hand, and the pilot against eval.py's flight."""

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

import shield_nav.evaluation as E
from envs.config import ConfigError
from envs.navigation import NavigationEnv
from envs.navigation import interface as I
from envs.navigation.config import ActionConfig
from shield_nav.deploy import ShieldedPilot, fly
from shield_nav.evaluation.rollout import flown_scene, nav_config, sample_trial, trial_seed
from shield_nav.safety.escape import EscapeConfig, StallEscape
from shield_nav.safety.shield import ShieldConfig

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FULL = os.path.join(ROOT, "checkpoints", "full")
G = 9.81


def _yaw(psi):
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]])


def test_policy_state_by_hand():
    # Heading 90 deg (body x along world +y), at (0, 0, 1.5), goal (0, 20, 3): the offset (0, 20) seen from the
    # heading frame is 20 m straight ahead, so goal_xy_h = (20, 0) / max(20, 10) = (1, 0); z 1.5 / 3 = 0.5,
    # z_goal 3 / 3 = 1, speed 5 / 10 = 0.5. Close by (5 m to the vehicle's left) the offset is not normalised to
    # 1: (0, 5) / max(5, 10) = (0, 0.5).
    R = _yaw(math.pi / 2)
    prev = np.array([[0.1, -0.2, 0.3, -0.4]])
    s = I.policy_state(np.array([[0.0, 0.0, 1.5]]), R, np.array([[2.0, 0.0, -1.0]]), prev,
                       np.array([[0.0, 20.0, 3.0]]), np.array([5.0]))  # fmt: skip
    assert s.shape == (1, 21)
    np.testing.assert_allclose(s[0, 0:3], [0.2, 0.0, -0.1])
    np.testing.assert_array_equal(s[0, 3:12], R.reshape(9))
    np.testing.assert_array_equal(s[0, 12:16], prev[0])
    np.testing.assert_allclose(s[0, 16:18], [1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(s[0, 18:21], [0.5, 1.0, 0.5])
    near = I.policy_state(np.zeros((1, 3)), _yaw(0.0), np.zeros((1, 3)), np.zeros((1, 4)), np.array([[0.0, 5.0, 0.0]]),
                          np.array([3.0]))  # fmt: skip
    np.testing.assert_allclose(near[0, 16:18], [0.0, 0.5])


def test_action_command_mapping_by_hand():
    cfg = ActionConfig()  # thrust 2 .. 25 m/s^2, tilt 45 deg, yaw lead 60 deg, from the heading
    base = np.array([0.3, 0.3, 0.3])
    a = np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 0.5, -0.5, 1.0], [-1.0, -1.0, 1.0, -0.5]])
    cmd = I.action_to_command(a, base, cfg, G)
    # 0 -> hover thrust g; +1 -> 25; -1 -> 2; 0.5 x 45 deg = 22.5 deg; yaw 0.3 rad + 60 deg / -30 deg
    expect = np.array([[G, 0.0, 0.0, 0.3],
                       [25.0, math.radians(22.5), -math.radians(22.5), 0.3 + math.radians(60)],
                       [2.0, -math.radians(45), math.radians(45), 0.3 - math.radians(30)]])  # fmt: skip
    np.testing.assert_allclose(cmd, expect, atol=1e-12)
    np.testing.assert_allclose(I.command_to_action(cmd, base, cfg, G), a, atol=1e-12)
    # Half-way thrusts: 0.5 -> g + 0.5 (25 - g); -0.5 -> g - 0.5 (g - 2)
    half = I.action_to_command(np.array([[0.5, 0, 0, 0], [-0.5, 0, 0, 0]]), base[:2], cfg, G)[:, 0]
    np.testing.assert_allclose(half, [G + 0.5 * (25 - G), G - 0.5 * (G - 2)])
    # The velocity yaw base: moving along +y at 2 m/s (above yaw_base_speed 1) with heading 0 leads from 90 deg;
    # at 0.5 m/s, half-way (45 deg); at rest, from the heading.
    vcfg = ActionConfig(yaw_base="velocity")
    R = np.repeat(_yaw(0.0), 3, axis=0)
    v = np.array([[0.0, 2.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(I.yaw_bases(vcfg, R, v), [math.pi / 2, math.pi / 4, 0.0], atol=1e-15)
    np.testing.assert_array_equal(I.yaw_bases(cfg, R, v), np.zeros(3))


@pytest.fixture(scope="module")
def eval_full_trial():
    """eval.py's Full row (onnxruntime, default shield), one pinned trial on an ablation scene at 9 m/s."""
    cfg = E.load_eval_config(None, ["name=deploy", "configurations=[full]", "scenes.family=ablation",
                                    "scenes.indices=[7]", "speeds=[9.0]", "trials_per_scene=1", "plots=false",
                                    "network=export", "env_overrides=[episode.timeout_factor=1.5]"])  # fmt: skip
    (spec,) = E.plan_units(E.prepare(cfg))
    return cfg, spec, E.run_unit(spec)["trials"][0]


def test_pilot_flies_evals_full_flight_step_for_step(eval_full_trial):
    """The pilot alone (state vector, action mapping and shield outside the env) flies eval.py's Full trial: the
    same outcome, step count, shield activity and end point."""
    cfg, spec, rec = eval_full_trial
    env = NavigationEnv(config=nav_config(cfg, spec.family, spec.index, spec.speed, 1, spec.policy_env))
    seed = trial_seed(cfg.seed, spec.family, spec.index, spec.speed, 0)
    trial = sample_trial(flown_scene(cfg, spec.family, spec.index), env.field_stack, 0, seed,
                         env.cfg.vehicle.airframe.collision_radius + 0.4)  # fmt: skip
    assert trial["start"] == rec["start"] and trial["goal"] == rec["goal"]
    pilot = ShieldedPilot.load(FULL)
    r = fly(pilot, env, trial["start"], trial["goal"], spec.speed, trial["yaw"], seed % (2**31))
    assert (r["outcome"], r["steps"]) == (rec["outcome"], rec["steps"])
    assert round(r["shield_active"] * r["steps"]) == rec["shield"]["active_steps"] > 0
    np.testing.assert_array_equal(np.round(env.local_pos[0], 3), rec["traj"][-1][:3])
    env.close()


def test_pilot_with_handover_flies_evals_handed_flight_step_for_step():
    """With a handover the pilot flies eval.py's handed flight: a row handing every flight to the camera-map planner
    at 0.2 s (1 km of progress asked), the same outcome, step count, handed steps, shield activity and end point; the
    default rules are the `full_handover` row's. The flight is cut at 5 s (500 steps)."""
    over = {"kind": "handover", "window_s": 0.2, "min_progress": 1000.0}
    rows = [f"rows.mine.{k}={v}" for k, v in (("policy", "full"), ("shield", "true"), ("escape", "true"))]
    rows += [f"rows.mine.escape_overrides.{k}={v}" for k, v in over.items()]
    cfg = E.load_eval_config(None, ["name=deploy", "configurations=[mine]", *rows, "scenes.family=ablation",
                                    "scenes.indices=[7]", "speeds=[9.0]", "trials_per_scene=1", "plots=false",
                                    "network=export", "env_overrides=[episode.timeout_factor=0.0]"])  # fmt: skip
    (spec,) = E.plan_units(E.prepare(cfg))
    rec = E.run_unit(spec)["trials"][0]
    assert rec["escape"] == {"escapes": 1, "escape_steps": rec["steps"] - 20, "by_circling": 0}
    env = NavigationEnv(config=nav_config(cfg, spec.family, spec.index, spec.speed, 1, spec.policy_env))
    seed = trial_seed(cfg.seed, spec.family, spec.index, spec.speed, 0)
    trial = sample_trial(flown_scene(cfg, spec.family, spec.index), env.field_stack, 0, seed,
                         env.cfg.vehicle.airframe.collision_radius + 0.4)  # fmt: skip
    pilot = ShieldedPilot.load(FULL, handover=EscapeConfig(**over))
    r = fly(pilot, env, trial["start"], trial["goal"], spec.speed, trial["yaw"], seed % (2**31))
    assert (r["outcome"], r["steps"], r["handed_steps"]) == (rec["outcome"], rec["steps"], rec["steps"] - 20)
    assert round(r["shield_active"] * r["steps"]) == rec["shield"]["active_steps"]
    np.testing.assert_array_equal(np.round(env.local_pos[0], 3), rec["traj"][-1][:3])
    env.close()
    rules = ShieldedPilot.load(FULL, handover=True).handover
    assert (rules.kind, rules.window_s, rules.circle_turns, rules.circle_window_s) == ("handover", 5.0, 1.5, 10.0)


def test_pilot_planning_on_its_own_thread_flies_evals_delayed_plans_step_for_step():
    """``replan_delay=2``: the camera-map plans run on the pilot's planning thread and are flown two steps after
    their inputs; eval.py flies the same delay inline (``baselines.reactive.camera_map.plan_delay_steps=2``). The
    handed flight through the pilot, paced at the control period as on a vehicle (``real_time``), repeats eval.py's
    (outcome, steps, handed steps, shield activity, end point), and the delay is real: the same flight planned
    without it ends elsewhere. The flights are cut at 5 s (500 steps), 480 of them handed over."""
    over = {"kind": "handover", "window_s": 0.2, "min_progress": 1000.0}
    rows = [f"rows.mine.{k}={v}" for k, v in (("policy", "full"), ("shield", "true"), ("escape", "true"))]
    rows += [f"rows.mine.escape_overrides.{k}={v}" for k, v in over.items()]
    base = ["name=deploy", "configurations=[mine]", *rows, "scenes.family=ablation", "scenes.indices=[7]",
            "speeds=[9.0]", "trials_per_scene=1", "plots=false", "network=export",
            "env_overrides=[episode.timeout_factor=0.0]"]  # fmt: skip
    recs = {}
    for delay in (0, 2):
        cfg = E.load_eval_config(None, [*base, f"baselines.reactive.camera_map.plan_delay_steps={delay}"])
        (spec,) = E.plan_units(E.prepare(cfg))
        recs[delay] = E.run_unit(spec)["trials"][0]
    rec = recs[2]
    assert recs[0]["traj"][-1] != rec["traj"][-1]
    env = NavigationEnv(config=nav_config(cfg, spec.family, spec.index, spec.speed, 1, spec.policy_env))
    seed = trial_seed(cfg.seed, spec.family, spec.index, spec.speed, 0)
    trial = sample_trial(flown_scene(cfg, spec.family, spec.index), env.field_stack, 0, seed,
                         env.cfg.vehicle.airframe.collision_radius + 0.4)  # fmt: skip
    with ShieldedPilot.load(FULL, handover=EscapeConfig(**over), replan_delay=2) as pilot:
        assert pilot._pool is not None
        t0 = time.perf_counter()  # paced at the control period, as on a vehicle: the thread plans in the idle time
        r = fly(pilot, env, trial["start"], trial["goal"], spec.speed, trial["yaw"], seed % (2**31), real_time=True)
        assert time.perf_counter() - t0 >= (r["steps"] - 1) * env.cfg.vehicle.command_dt
    with pytest.raises(RuntimeError, match="shutdown"):  # closed: its planning thread takes no more plans
        pilot._pool.submit(int)
    assert (r["outcome"], r["steps"], r["handed_steps"]) == (rec["outcome"], rec["steps"], rec["steps"] - 20)
    assert round(r["shield_active"] * r["steps"]) == rec["shield"]["active_steps"]
    np.testing.assert_array_equal(np.round(env.local_pos[0], 3), rec["traj"][-1][:3])
    env.close()
    with pytest.raises(ValueError, match="replan_delay: 2; it delays the handover planner's plans"):
        ShieldedPilot(pilot.policy, replan_delay=2)
    with pytest.raises(ValueError, match="replan_delay: -1"):
        ShieldedPilot(pilot.policy, handover=True, replan_delay=-1)
    with pytest.raises(ConfigError, match=r"baselines\.reactive\.camera_map\.plan_delay_steps"):
        E.load_eval_config(None, [*base, "baselines.reactive.camera_map.plan_delay_steps=-1"])
    with pytest.raises(ValueError, match=r"escape\.plan_delay_steps 2; the escape plans inline"):
        StallEscape(EscapeConfig(kind="handover", plan_delay_steps=2), 1, 0.01)
    with pytest.raises(E.EvalError, match=r"'mine': escape\.plan_delay_steps must be 0"):
        E.resolve_rows(E.load_eval_config(None, [*base, "escape.plan_delay_steps=2"]))


def test_warm_up_leaves_the_pilots_flights_as_they_were():
    """``load`` warms a pilot up (a scratch pilot flies three made-up steps, one handed over): the pilot still asks
    for a reset, and then flies the same commands, shield activity and handovers, step for step, as a pilot loaded
    without the warm-up, also when warmed up again in mid-flight (its memories, maps and stall clocks untouched)."""
    warm = ShieldedPilot.load(FULL, num_vehicles=2, handover=True)
    cold = ShieldedPilot.load(FULL, num_vehicles=2, handover=True, warm_up=False)
    with pytest.raises(RuntimeError, match="call reset"):
        warm.step(np.full((2, 1, 60, 100), 5.0), np.ones((2, 3)), np.zeros((2, 3)), np.repeat(_yaw(0), 2, 0))
    volume = ([0.0, -16.0, 0.0], [64.0, 16.0, 4.0])
    for p in (warm, cold):
        p.reset([[60.0, 0.0, 1.5], [60.0, 3.0, 1.5]], [3.0, 5.0], volume=volume)
    rng = np.random.default_rng(3)
    pos = np.array([[5.0, 0.0, 1.5], [5.0, 3.0, 1.2]])
    vel, R = np.array([[2.0, 0.0, 0.0], [3.0, 0.5, 0.0]]), np.repeat(_yaw(0.1), 2, 0)
    for t in range(6):
        depth = rng.uniform(2.0, 8.0, (2, 1, 60, 100))
        if t == 3:
            for p in (warm, cold):  # vehicle 1 stalls: the planner flies it from now on
                p._escape.guided[1] = True
        if t in (2, 4):
            warm.warm_up()
        a, b = warm.step(depth, pos, vel, R), cold.step(depth, pos, vel, R)
        np.testing.assert_array_equal(a.command, b.command)
        assert a.shield.active.tolist() == b.shield.active.tolist() and a.handed.tolist() == b.handed.tolist()
        pos = pos + 0.01 * vel
    assert a.handed.tolist() == [False, True]


def test_pilot_refuses_bad_input():
    pilot = ShieldedPilot.load(FULL, num_vehicles=2)
    depth, pos, vel, R = np.full((2, 1, 60, 100), 5.0), np.ones((2, 3)), np.zeros((2, 3)), np.repeat(_yaw(0), 2, 0)
    with pytest.raises(RuntimeError, match="call reset"):
        pilot.step(depth, pos, vel, R)
    with pytest.raises(ValueError, match="target_speed"):
        pilot.reset([[60.0, 0.0, 1.5]], [5.0, -1.0])
    pilot.reset([[60.0, 0.0, 1.5]], 5.0)
    with pytest.raises(ValueError, match=r"depth_m must have shape \(2, 1, 60, 100\)"):
        pilot.step(depth[:, :, :30], pos, vel, R)
    bad = pos.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="pos is not finite"):
        pilot.step(depth, bad, vel, R)
    scaled, mirrored = R.copy(), R.copy()  # not rotations: a scaled matrix, and a reflection (det -1)
    scaled[1] *= 1.01
    mirrored[0, :, 1] *= -1.0
    with pytest.raises(ValueError, match=r"vehicle 1 is not a rotation \(\|R\^T R - I\| = 0.0201, det = 1.03\)"):
        pilot.step(depth, pos, vel, scaled)
    with pytest.raises(ValueError, match=r"R_wb of vehicle 0 is not a rotation \(\|R\^T R - I\| = 0, det = -1\)"):
        pilot.step(depth, pos, vel, mirrored)
    rounded = (R.astype(np.float32) @ _yaw(0.3).astype(np.float32)).astype(np.float64)  # float32 rounding: taken
    pilot.step(depth, pos, vel, rounded)
    pilot.reset([[60.0, 0.0, 1.5]], 5.0)
    out = pilot.step(depth, pos, vel, R)  # a wall 5 m ahead, hovering: a finite command per vehicle
    assert out.command.shape == (2, 4) and np.isfinite(out.command).all() and out.shield is not None
    with pytest.raises(ValueError, match="hypotheses"):
        ShieldedPilot(pilot.policy, ShieldConfig(hypotheses="first_clean"))
    with pytest.raises(TypeError, match="shield"):
        ShieldedPilot(pilot.policy, {"r_safe": 0.3})
    handing = ShieldedPilot(pilot.policy, num_vehicles=2, handover=True)
    with pytest.raises(ValueError, match=r"volume=\(lo, hi\)"):
        handing.reset([[60.0, 0.0, 1.5]], 5.0)
    with pytest.raises(ValueError, match="every vehicle starts"):
        handing.reset([[60.0, 0.0, 1.5]], 5.0, ids=[1], volume=([0, -16, 0], [64, 16, 4]))
    handing.reset([[60.0, 0.0, 1.5]], 5.0, volume=([0.0, -16.0, 0.0], [64.0, 16.0, 4.0]))
    out = handing.step(depth, pos, vel, R)
    assert out.handed.tolist() == [False, False] and np.isfinite(out.command).all()
    with pytest.raises(ValueError, match=r"handover\.kind: 'map'"):
        ShieldedPilot(pilot.policy, handover=EscapeConfig(kind="map"))
    with pytest.raises(ConfigError, match=r"handover\.window_s"):
        ShieldedPilot(pilot.policy, handover=EscapeConfig(kind="handover", window_s=0.0))
    with pytest.raises(ConfigError, match=r"handover\.handover_planner"):
        ShieldedPilot(pilot.policy, handover=EscapeConfig(kind="handover", handover_planner="autopilot"))
    with pytest.raises(ValueError, match=r"handover_planner: 'expert' reads the scene's map"):
        ShieldedPilot(pilot.policy, handover=EscapeConfig(kind="handover", handover_planner="expert"))


def test_pilot_keeps_inside_its_geofence():
    """With ``shield.fence`` the pilot's shield brakes an approach to the fence by the hand-computed braking row
    (vehicle 0: 2 m from x_hi = 10 at 5 m/s, no lag: a_x <= -b, b = -4 (sqrt(34) - 5) + 50 / sqrt(34)) and leaves
    vehicle 1, in the middle of the box, to the policy; the box is checked at reset."""
    policy = ShieldedPilot.load(FULL, num_vehicles=2).policy
    pilot = ShieldedPilot(policy, ShieldConfig(lag_s=0.0, fence=True), num_vehicles=2)
    assert pilot.warm_up() > 0  # the warm-up's scratch pilot gets a fence of its own
    with pytest.raises(ValueError, match="shield.fence is on"):
        pilot.reset([[60.0, 0.0, 1.5]], 5.0)
    with pytest.raises(ValueError, match="shield.fence is off"):
        ShieldedPilot(policy, num_vehicles=2).reset([[60.0, 0.0, 1.5]], 5.0, fence=[[0.0, 0.0], [10.0, 10.0]])
    pilot.reset([[60.0, 5.0, 1.5]], 5.0, fence=[[0.0, 0.0], [10.0, 10.0]])
    depth = np.zeros((2, 1, 60, 100))  # no return anywhere: the fence is the only obstacle
    pos, vel = np.array([[8.0, 5.0, 1.5], [5.0, 5.0, 1.5]]), np.array([[5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    out = pilot.step(depth, pos, vel, np.repeat(_yaw(0.0), 2, 0))
    b = -4.0 * (math.sqrt(34.0) - 5.0) + 50.0 / math.sqrt(34.0)
    raw, safe = out.shield.accel_raw, out.shield.accel_safe
    assert raw[0, 0] > -b and out.shield.active.tolist() == [True, False]
    np.testing.assert_allclose(safe[0], [-b, raw[0, 1], raw[0, 2]], atol=1e-6)  # the projection onto a_x <= -b
    np.testing.assert_array_equal(safe[1], raw[1])


def test_deploy_cli_flies_the_evaluations_trial(eval_full_trial):
    _, _, rec = eval_full_trial
    out = subprocess.run([sys.executable, "-m", "shield_nav.deploy", FULL, "--family", "ablation", "--scene", "7",
                          "--speed", "9"], capture_output=True, text=True, cwd=ROOT, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert f"{rec['outcome']} after {rec['steps'] / 100:.2f} s" in out.stdout
    assert "per control step, mean / p99: the whole step" in out.stdout and "and the shield" in out.stdout
    assert f"of {rec['steps']} steps over the 10 ms control period (back to back; --real-time paces them)" in out.stdout


def test_deploy_cli_hands_over_with_full_handovers_rules(eval_full_trial, capsys):
    """`--handover`: this trial never stalls (5 s without a metre of progress), so it flies as without and says
    that the planner flew none of it."""
    from shield_nav.deploy import main

    _, _, rec = eval_full_trial
    assert main([FULL, "--family", "ablation", "--scene", "7", "--speed", "9", "--handover"]) == 0
    out = capsys.readouterr().out
    assert f"handed to the camera-map planner for 0.00 s, ablation scene 7, 9 m/s, trial 0: {rec['outcome']} after " \
           f"{rec['steps'] / 100:.2f} s" in out  # fmt: skip


def test_deploy_cli_shield_settings_are_checked_before_flying():
    from shield_nav.deploy import main

    with pytest.raises(ConfigError, match="depth_filter"):
        main([FULL, "--shield", "depth_filter=gauss"])
    with pytest.raises(ConfigError, match="no_such_key"):
        main([FULL, "--shield", "no_such_key=1"])
    with pytest.raises(SystemExit):  # argparse: --shield with --no-shield
        main([FULL, "--no-shield", "--shield", "depth_filter=median_cross"])
