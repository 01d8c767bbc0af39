"""The onboard scene memory (``env.scene_memory``): stored points and sector read-out against hand-computed values."""

import math

import numpy as np
import pytest

from envs.camera.config import CameraConfig
from envs.camera.model import ray_grid
from envs.config import ConfigError
from envs.navigation import NavigationEnv
from envs.navigation.config import SceneMemoryConfig
from envs.navigation.memory import SceneMemory
from envs.vehicle.rotations import euler_zyx_to_rot

CAM = CameraConfig()  # level mount, 0.1 m ahead of the body origin, 10 m range


def yaw_rot(*yaw_deg):
    y = np.radians(yaw_deg)
    return euler_zyx_to_rot(np.zeros(len(y)), np.zeros(len(y)), y)


def test_stored_points_are_the_in_band_returns_placed_with_the_pose():
    mem = SceneMemory(SceneMemoryConfig(enabled=True, band=0.5, pixel_stride=4, interval=1), CAM, 2)
    x_u, _ = ray_grid(CAM)
    cols = np.arange(2, 100, 4)
    depth = np.full((2, 1, 60, 100), 4.0, dtype=np.float32)  # a wall 4 m in front of the lens
    pos = np.array([[1.0, 2.0, 1.5], [1.0, 2.0, 1.5]])
    mem.push(depth, pos, yaw_rot(0.0, 90.0), np.array([True, True]))
    # Level camera: a pixel at optical depth z lies z ahead of the lens, z * x_u to the right; it is in the band
    # when |z * y_v| <= 0.5, true of the rows near the middle, and every row of a column lies as far horizontally.
    ahead, right = 0.1 + 4.0, 4.0 * x_u[cols]
    want0 = np.stack((1.0 + ahead * np.ones(25), 2.0 - right), axis=1)  # yaw 0: x forward, y left
    want1 = np.stack((1.0 + right, 2.0 + ahead * np.ones(25)), axis=1)  # yaw 90 deg: forward is +y, right is +x
    np.testing.assert_allclose(mem.points[0, 0], want0, atol=1e-5)
    np.testing.assert_allclose(mem.points[1, 0], want1, atol=1e-5)
    assert mem.valid[:, 0].all() and not mem.valid[:, 1:].any()


def test_out_of_band_far_and_missing_returns_are_not_stored():
    mem = SceneMemory(SceneMemoryConfig(enabled=True, band=0.5, interval=1), CAM, 3)
    depth = np.zeros((3, 60, 100), dtype=np.float32)
    depth[0, :8] = 4.0  # only the top rows: 4 * |y_v| >= 1.6 m above the vehicle, outside the 0.5 m band
    depth[1] = CAM.max_range  # no return
    depth[2] = 4.0  # a valid wall, but no new frame this step
    pos = np.zeros((3, 3))
    mem.push(depth, pos, yaw_rot(0.0, 0.0, 0.0), np.array([True, True, False]))
    assert not mem.valid.any()


def test_frames_are_stored_every_interval_steps_into_a_ring_and_forgotten_on_reset():
    cfg = SceneMemoryConfig(enabled=True, frames=3, interval=2)
    mem = SceneMemory(cfg, CAM, 1)
    pos, rot, yes = np.zeros((1, 3)), yaw_rot(0.0), np.array([True])
    for k in range(5):  # depth 1..5 m: frames of steps 0, 2, 4 are stored (every second step)
        mem.push(np.full((1, 60, 100), 1.0 + k, dtype=np.float32), pos, rot, yes)
    np.testing.assert_allclose(mem.points[0, :, 0, 0], [1.1, 3.1, 5.1], atol=1e-6)
    mem.push(np.full((1, 60, 100), 6.0, dtype=np.float32), pos, rot, yes)  # step 5: not due
    mem.push(np.full((1, 60, 100), 7.0, dtype=np.float32), pos, rot, yes)  # step 6: replaces the oldest
    np.testing.assert_allclose(mem.points[0, :, 0, 0], [7.1, 3.1, 5.1], atol=1e-6)
    mem.reset(np.array([0]))
    assert not mem.valid.any()
    mem.push(np.full((1, 60, 100), 2.0, dtype=np.float32), pos, rot, yes)  # the first frame after a reset is stored
    assert mem.valid[0].sum() == 25


def test_read_out_is_the_nearest_remembered_distance_per_heading_sector():
    cfg = SceneMemoryConfig(enabled=True, bins=16, range=5.0, frames=2)
    mem = SceneMemory(cfg, CAM, 2)
    # Vehicle 0 at (1, 1) heading +y (90 deg). Points: 2 m ahead (sector 8: [0, 22.5) deg), 3 m to its left
    # (world -x; 90 deg, sector 12) and 4 m to its left in the same sector, one 6 m behind (beyond the range).
    pts = {(0, 0, 0): (1.0, 3.0), (0, 0, 1): (-2.0, 1.0), (0, 1, 0): (-3.0, 1.0), (0, 1, 1): (1.0, -5.0)}
    for (e, f, c), xy in pts.items():
        mem.points[e, f, c] = xy
        mem.valid[e, f, c] = True
    # Vehicle 1 at the origin heading 0: one point 1 m at -100 deg (its right, behind): sector floor(80 / 22.5) = 3.
    mem.points[1, 0, 0] = (math.cos(math.radians(-100.0)), math.sin(math.radians(-100.0)))
    mem.valid[1, 0, 0] = True
    mem.points[1, 1, 0] = (0.0, 0.5)  # stored but not valid: ignored
    out = mem.observe(np.array([[1.0, 1.0, 1.5], [0.0, 0.0, 1.5]]), yaw_rot(90.0, 0.0))
    want = np.ones((2, 16), dtype=np.float32)
    want[0, 8], want[0, 12], want[1, 3] = 2.0 / 5.0, 3.0 / 5.0, 1.0 / 5.0
    np.testing.assert_allclose(out, want, atol=1e-6)
    assert out.dtype == np.float32


def test_env_gives_the_memory_group_only_when_enabled_and_names_bad_keys():
    small = {"scenes.indices": [0, 1]}
    env = NavigationEnv(num_envs=3, overrides={**small, "scene_memory.enabled": True, "scene_memory.bins": 8})
    obs, _ = env.reset(seed=0)
    assert obs["memory"].shape == (3, 8) and env.single_observation_space["memory"].shape == (8,)
    assert ((obs["memory"] > 0) & (obs["memory"] <= 1)).all()
    for _ in range(3):
        obs, *_ = env.step(np.zeros((3, 4)))
    assert obs["memory"].shape == (3, 8) and np.isfinite(obs["memory"]).all()
    plain = NavigationEnv(num_envs=2, overrides=small)
    assert "memory" not in plain.reset(seed=0)[0] and "memory" not in plain.single_observation_space.spaces
    for key, bad in (("bins", 0), ("range", -1.0), ("frames", 0), ("interval", 0), ("band", 0.0)):
        with pytest.raises(ConfigError, match=rf"scene_memory\.{key}"):
            NavigationEnv(num_envs=1, overrides={**small, f"scene_memory.{key}": bad})
