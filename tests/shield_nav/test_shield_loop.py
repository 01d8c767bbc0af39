"""The shield in the training loop (shield_nav/training/shield_loop.py, envs/rsl_rl.py ``command_filter``)."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from envs.navigation import NavigationEnv
from envs.rsl_rl import RslRlVecEnv
from shield_nav.algorithms.baselines import BaselineConfig, make_baseline
from shield_nav.safety.shield import HOCBFShield, ShieldConfig
from shield_nav.training.config import ConfigError, load_train_config
from shield_nav.training.shield_loop import ShieldInLoop

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
W = 0.01  # intervention penalty per m/s^2 of correction
SMALL = {"scenes.indices": [0, 1]}  # randomization on: both envs draw it from the same seed
# Two vehicles that fly straight at their goals at 9 m/s through ablation-family clutter: the shield must act.
OPTS = {"scene_ids": [0, 1], "start": [[0.5, 1.0, 1.5]] * 2, "goal": [[63.5, 2.0, 1.5]] * 2, "speed": [9.0, 9.0],
        "yaw": [0.0, 0.0]}  # fmt: skip


def _env():
    env = NavigationEnv(num_envs=2, **SMALL)
    env.reset(seed=0, options=OPTS)
    return env


def test_the_adapter_flies_exactly_what_an_independent_shield_commands():
    # With the intervention penalty on: the reward is the env's minus W x the independent shield's correction.
    looped, ref, alone = _env(), _env(), _env()
    # The shield without its local map, as the shipped Full's training loop has it (recipe_full.yaml).
    vec = RslRlVecEnv(looped, command_filter=ShieldInLoop(ShieldConfig(map_seconds=0.0), looped.cfg.camera),
                      filter_penalty=W)  # fmt: skip
    looped.reset(seed=0, options=OPTS)  # the adapter's own reset drew random episodes; restart both on OPTS
    shield = HOCBFShield(ShieldConfig(map_seconds=0.0), ref.cfg.camera)
    goal = make_baseline("goal", BaselineConfig())
    goal.reset(ref)
    active_steps, corrections = 0, []
    for _ in range(150):
        act = np.clip(ref.command_to_action(goal.commands(ref)), -1.0, 1.0)
        out = shield.filter(ref.action_to_command(act), ref.local_pos, ref.vehicles.vel_w, depth=ref.sensor_depth_buf,
                            R_wb=ref.vehicles.R_wb)  # fmt: skip
        _, rew, term, trunc, _ = ref.step(act, commands=out.command)
        shield.reset(np.flatnonzero(term | trunc))
        alone.step(act)
        _, vec_rew, done, extras = vec.step(torch.from_numpy(act))
        np.testing.assert_array_equal(looped.local_pos, ref.local_pos)
        np.testing.assert_array_equal(looped.vehicles.vel_w, ref.vehicles.vel_w)
        np.testing.assert_array_equal(done.numpy(), term | trunc)
        assert float(extras["log"]["shield/active"]) == pytest.approx(out.active.mean())
        corr = np.sqrt(np.sum((out.accel_safe - out.accel_raw) ** 2, axis=1))
        assert np.all(corr[~out.active] == 0.0)  # an unchanged command costs nothing
        np.testing.assert_allclose(vec_rew.numpy(), rew - W * corr, rtol=1e-6, atol=1e-6)
        assert float(extras["log"]["shield/correction"]) == pytest.approx(corr.mean(), rel=1e-6)
        assert float(extras["log"]["reward/shield"]) == pytest.approx(-W * corr.mean(), rel=1e-6)
        active_steps += int(out.active.sum())
        corrections.append(corr[out.active])
    assert active_steps > 20  # the shield acted, so the equality above says something
    assert np.concatenate(corrections).min() > 0.1  # and each act changed the acceleration (a penalty was paid)
    assert not np.array_equal(alone.local_pos, ref.local_pos)  # and what it did changed the flight


def test_a_finished_episode_forgets_the_shields_vehicle_state():
    env = _env()
    loop = ShieldInLoop(ShieldConfig(), env.cfg.camera)
    vec = RslRlVecEnv(env, command_filter=loop)
    for _ in range(3):
        vec.step(torch.zeros(2, 4))
    assert set(loop.shield._prev_vel) == {0, 1}  # the lag model keeps each vehicle's previous velocity
    loop.reset(np.array([1]))
    assert set(loop.shield._prev_vel) == {0}
    vec.set_curriculum_levels([0, 0])  # every episode restarts: nothing is kept
    assert loop.shield._prev_vel == {}


def test_shield_keys_of_the_train_config_are_checked_by_name():
    cfg = load_train_config(os.path.join(REPO, "configs/train/quick.yaml"),
                            ["shield_in_loop=true", "shield.brake_accel=9"])  # fmt: skip
    assert cfg.shield_in_loop and cfg.shield.brake_accel == 9.0 and cfg.shield.lag_s == ShieldConfig().lag_s
    with pytest.raises(ConfigError, match="shield.bogus"):
        load_train_config(os.path.join(REPO, "configs/train/quick.yaml"), ["shield.bogus=1"])
    with pytest.raises(ConfigError, match="shield.r_safe"):
        load_train_config(os.path.join(REPO, "configs/train/quick.yaml"), ["shield.r_safe=-1"])
    with pytest.raises(ConfigError, match="shield_penalty.*needs shield_in_loop"):
        load_train_config(os.path.join(REPO, "configs/train/quick.yaml"), ["shield_penalty=0.01"])
    for bad in ("-0.01", "nan", "inf"):
        with pytest.raises(ConfigError, match="shield_penalty"):
            load_train_config(os.path.join(REPO, "configs/train/quick.yaml"), ["shield_in_loop=true",
                                                                                 f"shield_penalty={bad}"])  # fmt: skip
    with pytest.raises(ValueError, match="filter_penalty"):
        RslRlVecEnv(_env(), filter_penalty=0.01)  # a penalty with no filter to pay it


def test_train_cli_with_the_shield_in_the_loop_logs_its_activity(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    root = str(tmp_path / "logs")
    args = ["--config", "configs/train/quick.yaml", "--num-envs", "4", "--set", "runner.num_steps_per_env=8",
            "--set", "shield_in_loop=true", "shield_penalty=0.01",
            "--max-iterations", "2", "--log-dir", root]  # fmt: skip
    res = subprocess.run([sys.executable, "train.py", *args], cwd=REPO, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-3000:]
    (run,) = [os.path.join(root, "quick", d) for d in os.listdir(os.path.join(root, "quick"))]
    acc = EventAccumulator(run)
    acc.Reload()
    values = [e.value for e in acc.Scalars("shield/active")]
    assert len(values) == 2 and all(0.0 <= v <= 1.0 for v in values)
    corr = [e.value for e in acc.Scalars("shield/correction")]
    paid = [e.value for e in acc.Scalars("reward/shield")]  # rsl-rl's per-iteration means of the step logs
    assert len(corr) == len(paid) == 2 and all(c >= 0 for c in corr)
    np.testing.assert_allclose(paid, [-0.01 * c for c in corr], rtol=1e-5, atol=1e-9)
    stored = torch.load(os.path.join(run, "model_1.pt"), weights_only=False)["infos"]["config"]
    assert stored["shield_in_loop"] is True and stored["shield"]["brake_accel"] == ShieldConfig().brake_accel
    assert stored["shield_penalty"] == 0.01


def test_view_penalty_by_hand_and_in_the_adapters_reward():
    from envs.rsl_rl import outside_view

    env = _env()
    half = np.radians(env.cfg.camera.hfov_deg) / 2.0
    yaw = np.radians(90.0)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    cases = [  # (heading rotation, velocity, expected penalty [rad])
        (np.eye(3), [3.0, 0.0, 0.0], 0.0),  # flying along the camera axis
        (np.eye(3), [0.0, 3.0, 0.0], np.pi / 2 - half),  # sideways at speed: 46.5 deg beyond the view
        (np.eye(3), [0.0, -1.0, 0.0], 0.5 * (np.pi / 2 - half)),  # sideways at 1 m/s: half the ramp
        (np.eye(3), [-3.0, 0.0, 0.0], np.pi - half),  # backwards
        (np.eye(3), [0.0, 0.4, 0.0], 0.0),  # hovering: below the ramp
        (np.eye(3), [0.0, 0.0, 5.0], 0.0),  # climbing straight up: no horizontal velocity
        (rz, [0.0, 3.0, 0.0], 0.0),  # heading +y, flying +y
        (rz, [3.0, 3.0, 0.0], np.pi / 4 - half),  # 45 deg off the axis: 1.5 deg beyond the view
    ]
    for rot, vel, want in cases:
        env.vehicles._qpos[0, 3:7] = _quat_of(rot)
        env.vehicles._qvel[0, :3] = vel
        assert outside_view(env)[0] == pytest.approx(want, abs=1e-9), (rot, vel)
    # In the adapter: the reward is the env's minus the weight times it, 0 on a step that ends an episode.
    a, b = _env(), _env()
    vec = RslRlVecEnv(a, view_penalty=0.5)
    a.reset(seed=0, options=OPTS)
    act = np.array([[0.2, 0.4, 0.0, 0.0], [0.2, -0.3, 0.2, 0.0]])  # rolls: the vehicles slide sideways
    paid = []
    for _ in range(60):
        _, rew, term, trunc, _ = b.step(act)
        want = 0.5 * np.where(term | trunc, 0.0, outside_view(b))
        _, vec_rew, _, extras = vec.step(torch.from_numpy(act))
        np.testing.assert_allclose(vec_rew.numpy(), (rew - want).astype(np.float32), rtol=1e-6, atol=1e-6)
        assert float(extras["log"]["reward/view"]) == pytest.approx(-want.mean(), abs=1e-7)
        paid.append(want.sum())
    assert sum(paid) > 0  # the rolled vehicles did slide outside the view, so the equality says something
    with pytest.raises(ValueError, match="view_penalty"):
        RslRlVecEnv(_env(), view_penalty=-1.0)
    with pytest.raises(ConfigError, match="view_penalty"):
        load_train_config(os.path.join(REPO, "configs/train/quick.yaml"), ["view_penalty=nan"])


def _quat_of(rot: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation about z."""
    yaw = np.arctan2(rot[1, 0], rot[0, 0])
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
