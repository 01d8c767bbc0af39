"""The shield's geofence (shield_nav/safety/fence.py, ``ShieldConfig.fence``): hand-computed rows and a flight."""

import math

import numpy as np
import pytest

from envs.config import ConfigError, load_config
from envs.navigation import NavigationEnv
from shield_nav.algorithms.baselines import BaselineConfig, make_baseline
from shield_nav.safety.fence import env_fence, fence_boxes, fence_points
from shield_nav.safety.shield import STATUS_SOLVED, HOCBFShield, ShieldConfig

G = 9.81
BOX = np.array([[0.0, 0.0], [10.0, 10.0]])  # [[x_lo, y_lo], [x_hi, y_hi]]
NOTHING = [np.zeros((0, 3))]


def test_fence_points_are_the_feet_of_the_perpendiculars_within_range():
    p = np.array([8.0, 5.0, 1.5])
    pts = fence_points(p, BOX, 10.0)
    # x = 0 is 8 m away, x = 10 2 m, y = 0 and y = 10 5 m: all four in range, each at the vehicle's height.
    np.testing.assert_array_equal(pts, [[0.0, 5.0, 1.5], [10.0, 5.0, 1.5], [8.0, 0.0, 1.5], [8.0, 10.0, 1.5]])
    np.testing.assert_array_equal(fence_points(p, BOX, 3.0), [[10.0, 5.0, 1.5]])  # only the wall within 3 m
    assert fence_points(p, BOX, 1.0).shape == (0, 3)


def test_the_fence_brakes_an_approach_by_the_braking_barrier_and_leaves_flight_along_it_alone():
    # Braking barrier, a_b = 10, gain 4, r_safe 0.3, no lag. Vehicle 2 m from the wall x = 10, closing at 5 m/s:
    # e = 2 - 0.3 = 1.7, s = sqrt(2 * 10 * 1.7) = sqrt(34), h = s - 5, and the row n.a >= b with n = -e_x,
    # b = -4 h + 10 * 5 / s - (25 - 25) / 2 = 5.2512...: a_x <= -5.2512. The other three walls ask nothing here,
    # so a hovering command (a_raw = 0) is projected onto a_x = -b.
    cfg = ShieldConfig(lag_s=0.0, fence=True)
    s = math.sqrt(34.0)
    b = -4.0 * (s - 5.0) + 50.0 / s
    cmd = np.array([[G, 0.0, 0.0, 0.0]])
    out = HOCBFShield(cfg).filter(cmd, np.array([[8.0, 5.0, 1.5]]), np.array([[5.0, 0.0, 0.0]]), points_w=NOTHING,
                                  fence=BOX)  # fmt: skip
    assert out.active[0] and out.status[0] == STATUS_SOLVED
    np.testing.assert_allclose(out.accel_safe[0], [-b, 0.0, 0.0], atol=1e-6)
    # The same speed along the wall: closing speed 0, b = -4 sqrt(34) - 25 / 2 < 0, nothing to correct.
    along = HOCBFShield(cfg).filter(cmd, np.array([[8.0, 5.0, 1.5]]), np.array([[0.0, 5.0, 0.0]]), points_w=NOTHING,
                                    fence=BOX)  # fmt: skip
    assert not along.active[0] and np.array_equal(along.command, cmd)
    # Without the fence the empty cloud asks nothing.
    off = HOCBFShield(ShieldConfig(lag_s=0.0)).filter(cmd, np.array([[8.0, 5.0, 1.5]]), np.array([[5.0, 0.0, 0.0]]),
                                                      points_w=NOTHING)  # fmt: skip
    assert not off.active[0]
    # An inset of 1 m moves the wall to x = 9: 1 m away, e = 0.7, s = sqrt(14).
    s1 = math.sqrt(14.0)
    inset = HOCBFShield(ShieldConfig(lag_s=0.0, fence=True, fence_inset=1.0)).filter(
        cmd, np.array([[8.0, 5.0, 1.5]]), np.array([[3.0, 0.0, 0.0]]), points_w=NOTHING, fence=BOX
    )
    b1 = -4.0 * (s1 - 3.0) + 30.0 / s1
    np.testing.assert_allclose(inset.accel_safe[0], [-b1, 0.0, 0.0], atol=1e-6)


def test_fence_inputs_are_checked():
    with pytest.raises(ValueError, match="shield.fence is off"):
        fence_boxes(BOX, 1, False, 0.0)
    with pytest.raises(ValueError, match="give each vehicle's fence box"):
        HOCBFShield(ShieldConfig(fence=True)).filter(np.array([[G, 0, 0, 0]]), np.zeros((1, 3)), np.zeros((1, 3)),
                                                     points_w=NOTHING)  # fmt: skip
    with pytest.raises(ValueError, match="lo < hi"):
        fence_boxes(np.array([[0.0, 0.0], [10.0, -1.0]]), 1, True, 0.0)
    with pytest.raises(ValueError, match="after the inset"):
        fence_boxes(BOX, 1, True, 5.0)  # a 10 m box inset by 5 m on each side is empty
    with pytest.raises(ValueError, match=r"\(3, 2, 2\)"):
        fence_boxes(np.zeros((2, 2, 2)), 3, True, 0.0)
    with pytest.raises(ConfigError, match="fence_inset"):
        load_config(ShieldConfig, overrides=["fence_inset=-1"])
    with pytest.raises(ConfigError, match="fence"):
        load_config(ShieldConfig, overrides=["fence=maybe"])


def test_a_flight_at_the_volume_side_stays_in_with_the_fence_and_leaves_without_it():
    # Two vehicles fly at 5 m/s towards a goal 20 m behind their start, out through the volume's side x = -3 (the
    # ablation scenes span x in [0, 64], out of bounds 3 m beyond): real physics and depth, the default shield.
    opts = {"scene_ids": [0, 1], "start": [[0.5, 1.0, 1.5]] * 2, "goal": [[-20.0, 1.0, 1.5]] * 2,
            "speed": [5.0, 5.0], "yaw": [math.pi, math.pi]}  # fmt: skip
    ends = {}
    for fence in (False, True):
        env = NavigationEnv(num_envs=2, **{"scenes.indices": [0, 1]})
        env.reset(seed=0, options=opts)
        np.testing.assert_array_equal(env_fence(env), [[[-3.0, -19.0], [67.0, 19.0]]] * 2)
        shield = HOCBFShield(ShieldConfig(fence=fence), env.cfg.camera)
        goal = make_baseline("goal", BaselineConfig())
        goal.reset(env)
        min_x, left, done = np.inf, np.zeros(2, dtype=bool), np.zeros(2, dtype=bool)
        for _ in range(300):
            act = np.clip(env.command_to_action(goal.commands(env)), -1.0, 1.0)
            out = shield.filter_env(env, env.action_to_command(act))
            _, _, term, trunc, info = env.step(act, commands=out.command)
            left |= np.asarray(info["out_of_bounds"], dtype=bool) & ~done
            done |= term | trunc
            if done.all():
                break
            min_x = min(min_x, float(env.local_pos[~done, 0].min()))
        ends[fence] = (left.copy(), min_x, done.copy())
    assert ends[False][0].all()  # without the fence both leave the volume
    assert not ends[True][2].any()  # with it neither leaves nor crashes in 3 s of pushing at the side
    assert -3.0 + 0.05 < ends[True][1] < -2.0  # and each comes to the fence, r_safe = 0.3 m inside it
