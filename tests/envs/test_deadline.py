"""The time limit as part of the task (``episode.deadline``) and the clock observation (``episode.clock_input``)."""

import numpy as np
import pytest

from envs.config import ConfigError
from envs.navigation import NavigationEnv

SMALL = {"scenes.indices": [0], "curriculum.enabled": False}


def test_clock_is_time_left_and_the_slack_over_the_distance_still_to_fly_by_hand():
    env = NavigationEnv(num_envs=4, overrides={**SMALL, "episode.clock_input": True})
    env.reset(seed=0)
    dt = env.cfg.vehicle.command_dt  # 0.01 s
    assert dt == pytest.approx(0.01)
    env.max_episode_length_buf[:] = [1000, 1000, 4000, 500]
    env.episode_length_buf[:] = [400, 950, 1000, 600]  # the last one is past its limit
    env.target_speed_buf[:] = [5.0, 3.0, 9.0, 7.0]
    env.goal_buf[:] = [[20.0, 0.0, 1.0], [0.0, 5.5, 1.0], [0.0, 15.0, 1.0], [3.0, 4.0, 1.0]]
    pos = np.array([[0.0, 0.0, 1.0]] * 4)
    left, slack = env.clock(pos)
    # 6 s left; 20 m away, 5 m radius -> 15 m to fly at 5 m/s = 3 s: twice the time, 2 / 3
    # 0.5 s left; 0.5 m to the radius, floored at 1 m: 0.5 * 3 / 1 = 1.5 -> 0.5
    # 30 s left; 10 m at 9 m/s: 27 times -> clipped to 1
    # past the limit: nothing left
    np.testing.assert_allclose(left, [6.0, 0.5, 30.0, 0.0])
    np.testing.assert_allclose(slack, [2.0 / 3.0, 0.5, 1.0, 0.0])


def test_a_time_out_terminates_only_with_deadline_terminate():
    for deadline, terminated in (("truncate", False), ("terminate", True)):
        env = NavigationEnv(num_envs=3, overrides={**SMALL, "episode.deadline": deadline})
        env.reset(seed=0)
        env.max_episode_length_buf[:] = env.episode_length_buf + 2  # two steps to every deadline
        _, _, term, trunc, info = env.step(np.zeros((3, 4)))
        assert not term.any() and not trunc.any()
        _, reward, term, trunc, info = env.step(np.zeros((3, 4)))
        assert (term == terminated).all() and (trunc == (not terminated)).all()
        assert (info["time_outs"] == (not terminated)).all()  # rsl-rl bootstraps only truncations
        assert info["log"]["episode/timeout"].tolist() == [1.0, 1.0, 1.0]
        assert (reward < 5.0).all()  # no success bonus (scale 10) on a time-out


def test_with_deadline_terminate_the_critic_ends_with_time_left_and_slack_and_the_clock_group_is_the_slack():
    plain = NavigationEnv(num_envs=2, overrides=SMALL)
    env = NavigationEnv(num_envs=2, overrides={**SMALL, "episode.deadline": "terminate", "episode.clock_input": True})
    _, info_plain = plain.reset(seed=0)
    obs, info = env.reset(seed=0)
    assert env.critic_dim == plain.critic_dim + 2 and info["critic"].shape == (2, plain.critic_dim + 2)
    np.testing.assert_array_equal(info["critic"][:, :-2], info_plain["critic"])  # the same vector before them
    for _ in range(3):
        obs, _, _, _, info = env.step(np.zeros((2, 4)))
    pos = env._field_cache[0]
    left, slack = env.clock(pos)
    np.testing.assert_allclose(info["critic"][:, -2], left / 30.0, rtol=1e-6)
    np.testing.assert_allclose(info["critic"][:, -1], slack, rtol=1e-6)
    np.testing.assert_allclose(obs["clock"][:, 0], slack, rtol=1e-6)
    assert env.single_observation_space["clock"].shape == (1,)
    # 3 steps into a limit of L steps: L - 3 steps are left
    np.testing.assert_allclose(left, (env.max_episode_length_buf - 3) * 0.01)
    assert "clock" not in plain.reset(seed=0)[0] and "clock" not in plain.single_observation_space.spaces


def test_a_bad_deadline_is_named():
    with pytest.raises(ConfigError, match=r"episode\.deadline.*'stop'"):
        NavigationEnv(num_envs=1, overrides={**SMALL, "episode.deadline": "stop"})
