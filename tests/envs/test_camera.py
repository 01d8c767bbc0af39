"""Depth camera: geometry against hand-worked values, exact agreement with mj_multiRay, bad input, point clouds."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from envs.camera import (
    CameraConfig,
    DepthCamera,
    R_bc,
    camera_poses,
    depth_to_points,
    intrinsics,
    key_slots,
    min_pool,
    normalize_depth,
    ray_dirs_c,
    save_depth_png,
    save_depth_strip,
    voxel_downsample,
    voxel_keys,
)
from envs.camera.reference import MjDepth, primitives_mjcf
from envs.config import ConfigError, load_config
from envs.scenes import FAMILIES, Box, Capsule, Cylinder, Sphere, make_scene
from envs.scenes.sdf import union_sdf

CFG = CameraConfig()


# ----------------------------------------------------------------------------- camera model
def test_intrinsics_span_the_field_of_view():
    fx, fy, cx, cy = intrinsics(CFG)
    # fx = (W/2) / tan(hfov/2) = 50 / tan(43.5 deg) = 52.688...; fy = 30 / tan(29 deg) = 54.122...
    assert fx == pytest.approx(50.0 / math.tan(math.radians(43.5)))
    assert fy == pytest.approx(30.0 / math.tan(math.radians(29.0)))
    assert (cx, cy) == (50.0, 30.0)
    d = ray_dirs_c(CFG)
    assert d.shape == (60, 100, 3)
    # Outer pixel centres sit half a pixel inside the image edges.
    assert math.degrees(math.atan(d[0, -1, 0])) == pytest.approx(math.degrees(math.atan(49.5 / fx)))


def test_mount_pitch_positive_looks_down():
    cfg = CameraConfig(mount_pitch_deg=30.0)
    R = R_bc(cfg)
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    # optical axis = Ry(30 deg) x_b = [cos 30, 0, -sin 30]; image right = -y_b
    assert np.allclose(R[:, 2], [math.cos(math.pi / 6), 0.0, -0.5])
    assert np.allclose(R[:, 0], [0.0, -1.0, 0.0])


def test_floor_depth_matches_hand_computed_formula():
    # Camera 1.5 m above an infinite floor, body yawed 30 deg and rolled 10 deg, mount pitched 25 deg down.
    cfg = CameraConfig(mount_pitch_deg=25.0, mount_pos_b=[0.0, 0.0, 0.0], max_range=50.0)
    cam = DepthCamera(cfg, [[]], floor_z=0.0)
    R_wb = Rotation.from_euler("ZYX", [30.0, 0.0, 10.0], degrees=True).as_matrix()
    depth = cam.render(np.array([[3.0, -2.0, 1.5]]), R_wb[None])[0, 0]
    # Ray t * R_wc (x_u, y_v, 1) from height 1.5 meets z = 0 at t = -1.5 / (R_wc d)_z, and t is the z-depth.
    d_w = ray_dirs_c(cfg) @ (R_wb @ R_bc(cfg)).T
    expect = np.where(d_w[..., 2] < 0, -1.5 / np.minimum(d_w[..., 2], -1e-12), np.inf)
    expect = np.clip(expect, cfg.min_range, cfg.max_range)
    assert np.allclose(depth, expect, rtol=1e-6, atol=1e-5)
    # Centre column, bottom row: looking 25 deg + (29 deg - half a pixel) below the horizon (roll 10 deg is
    # about the optical axis only at zero pitch, so just check a finite floor hit there).
    assert depth[-1, 50] < 3.0


def test_sphere_depth_matches_independent_ray_sphere():
    # Sphere of radius 1 centred 5 m ahead: hand check of the pixel nearest the axis, then every pixel.
    cfg = CameraConfig(mount_pos_b=[0.0, 0.0, 0.0])
    cam = DepthCamera(cfg, [[Sphere((5.0, 0.0, 0.0), 1.0)]])
    depth = cam.render(np.zeros((1, 3)), np.eye(3)[None])[0, 0]
    u = ray_dirs_c(cfg).reshape(-1, 3)
    n = np.linalg.norm(u, axis=1)
    u = u / n[:, None]
    c = np.array([0.0, 0.0, 5.0])  # sphere centre in the camera frame (optical axis = body x)
    b = u @ c
    disc = b * b - (c @ c - 1.0)
    dist = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)  # distance along unit rays
    expect = np.clip(dist / n, cfg.min_range, cfg.max_range).reshape(60, 100)  # z = dist * cos(angle)
    assert np.allclose(depth, expect, atol=1e-5)
    # The four central pixels look 0.5 px off axis: z is just above 4 m (the sphere's front at 4 m).
    assert 4.0 < depth[30, 50] < 4.01


# ----------------------------------------------------------------------------- agreement with mj_multiRay
def _free_poses(scene, n, rng, clearance=0.3):
    lo, hi = np.asarray(scene.bounds_lo), np.asarray(scene.bounds_hi)
    cand = rng.uniform(lo + [-1.0, -1.0, 0.3], hi + [1.0, 1.0, -0.3], (20 * n, 3))
    cand = cand[union_sdf(scene.primitives, cand) > clearance][:n]
    # yaw anywhere, pitch and roll up to +-40 deg (banked, climbing, diving)
    ypr = np.c_[rng.uniform(-180, 180, n), rng.uniform(-40, 40, n), rng.uniform(-40, 40, n)]
    return cand, Rotation.from_euler("ZYX", ypr, degrees=True).as_matrix()


def _agreement(cfg, scene, pos_w, R_wb, t_moving=None):
    cam = DepthCamera(cfg, [scene])
    ref = MjDepth(cfg, mujoco.MjModel.from_xml_string(scene.to_mjcf()))
    if t_moving is not None and scene.moving:
        base = scene.moving_positions(t_moving)
        cam.set_moving_positions(0, base)
        ref.data.mocap_pos[:] = base
        ref.forward()
    ours, theirs = cam.render(pos_w, R_wb), ref.render(pos_w, R_wb)
    return np.abs(ours - theirs)


@pytest.mark.parametrize("family", FAMILIES)
def test_matches_mj_multiray_in_every_family(family):
    rng = np.random.default_rng(sorted(FAMILIES).index(family))
    worst = 1.0
    last = FAMILIES[family].size - 1
    for index, pitch in ((0, 0.0), (last, 20.0)):  # easiest and densest scene, level and pitched mounts
        scene = make_scene(family, index)
        cfg = CameraConfig(mount_pitch_deg=pitch)
        pos_w, R_wb = _free_poses(scene, 12, rng)
        err = _agreement(cfg, scene, pos_w, R_wb, t_moving=3.7)
        frac = float(np.mean(err <= 0.01))
        worst = min(worst, frac)
        assert frac >= 0.999, f"{family}[{index}] pitch {pitch}: {frac:.5f} within 1 cm, max error {err.max():.3f} m"
    print(f"{family}: worst fraction within 1 cm = {worst:.6f}")


def test_matches_mj_multiray_on_every_primitive_type_and_rolled_cameras():
    rng = np.random.default_rng(7)
    prims = []
    for i in range(100):
        c = rng.uniform(-5, 5, 3)
        k = i % 4
        if k == 0:
            prims.append(Sphere(c, rng.uniform(0.2, 1.0)))
        elif k == 1:
            prims.append(Cylinder(c, c + rng.normal(size=3) * 1.5, rng.uniform(0.03, 0.5)))
        elif k == 2:
            prims.append(Capsule(c, c + rng.normal(size=3) * 1.5, rng.uniform(0.03, 0.5)))
        else:
            prims.append(Box(c, rng.uniform(0.05, 1.0, 3), rng.normal(size=4)))
    cfg = CameraConfig(mount_pitch_deg=-15.0)
    pos = rng.uniform(-4, 4, (400, 3))
    pos = pos[union_sdf(prims, pos + 0.0) > 0.35][:24]
    R_wb = Rotation.random(len(pos), random_state=3).as_matrix()  # any roll, including upside down
    ours = DepthCamera(cfg, [prims]).render(pos, R_wb)
    theirs = MjDepth.from_xml(cfg, primitives_mjcf(prims)).render(pos, R_wb)
    assert np.mean(np.abs(ours - theirs) <= 0.01) >= 0.999
    assert np.mean(ours < cfg.max_range) > 0.25  # the images do see things


def test_scene_ids_pick_each_cameras_scene():
    a, b = make_scene("train", 0), make_scene("benchmark", 3)
    rng = np.random.default_rng(1)
    pa, Ra = _free_poses(a, 5, rng)
    pb, Rb = _free_poses(b, 5, rng)
    both = DepthCamera(CFG, [a, b])
    img = both.render(np.r_[pa, pb], np.r_[Ra, Rb], scene_ids=np.r_[[0] * 5, [1] * 5])
    assert np.array_equal(img[:5], DepthCamera(CFG, [a]).render(pa, Ra))
    assert np.array_equal(img[5:], DepthCamera(CFG, [b]).render(pb, Rb))
    # a lone Scene or a flat primitive list is one scene
    assert np.array_equal(img[:5], DepthCamera(CFG, a).render(pa, Ra))
    assert DepthCamera(CFG, list(b.primitives)).num_scenes == 1
    assert DepthCamera(CFG, a).render(np.zeros((0, 3)), np.zeros((0, 3, 3))).shape == (0, 1, 60, 100)


def test_moving_obstacle_update_moves_what_is_seen():
    cfg = CameraConfig(mount_pos_b=[0.0, 0.0, 0.0])
    scene = make_scene("dynamic", 0)
    cam = DepthCamera(cfg, [scene])
    m = cam.num_moving(0)
    assert m == len(scene.moving) > 0
    # Park every mover far away except mover 0, placed 3 m ahead of a camera at (5, 0, 1) looking +x.
    base = np.tile([63.0, 15.0, 0.0], (m, 1))
    base[0] = (8.0, 0.0, 0.0)
    cam.set_moving_positions(0, base)
    r = scene.moving[0].cylinder.radius
    static_only = DepthCamera(cfg, [scene.primitives]).render(np.array([[5.0, 0.0, 1.0]]), np.eye(3)[None])
    img = cam.render(np.array([[5.0, 0.0, 1.0]]), np.eye(3)[None])
    if static_only[0, 0, 30, 50] > 3.0 - r + 0.01:  # nothing static in front of the mover
        assert img[0, 0, 29:31, 49:51].min() == pytest.approx(3.0 - r, abs=2e-3)
    with pytest.raises(ValueError, match="moving obstacles"):
        cam.set_moving_positions(0, base[:-1])


# ----------------------------------------------------------------------------- bad input
def test_empty_scene_reads_max_range():
    img = DepthCamera(CFG, [[]]).render(np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)))
    assert img.shape == (2, 1, 60, 100) and img.dtype == np.float32
    assert np.all(img == CFG.max_range)


@pytest.mark.parametrize(
    "prim",
    [
        Sphere((0.0, 0.0, 0.0), 0.5),
        Cylinder((0.0, 0.0, -1.0), (0.0, 0.0, 1.0), 0.3),
        Capsule((1.0, 0.0, 0.0), (2.0, 0.0, 0.0), 1.2),
        Box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.9, 0.1, 0.3, 0.2)),
    ],
)
def test_camera_inside_an_obstacle_reads_min_range(prim):
    cfg = CameraConfig(mount_pos_b=[0.0, 0.0, 0.0])
    img = DepthCamera(cfg, [[prim, Sphere((5.0, 0.0, 0.0), 1.0)]]).render(np.zeros((1, 3)), np.eye(3)[None])
    assert np.all(img == cfg.min_range)


def test_camera_in_the_floor_slab_reads_min_range_and_below_it_sees_its_underside():
    cam = DepthCamera(CFG, [make_scene("train", 0)])
    # The floor is a 0.1 m slab under z = 0 (as in the scene's MJCF): inside it, the camera is in an obstacle.
    assert np.all(cam.render(np.array([[5.0, 0.0, -0.05]]), np.eye(3)[None]) == CFG.min_range)
    # Under the slab, looking level: the upper half of the image sees its underside at z = -0.1 from z = -0.5,
    # the top row at z-depth 0.4 / tan(29 deg - half a pixel) (hand formula: height / slope of the ray).
    img = cam.render(np.array([[5.0, 0.0, -0.5]]), np.eye(3)[None])[0, 0]
    _, fy, _, cy = intrinsics(CFG)
    assert img[0, 50] == pytest.approx(0.4 / ((cy - 0.5) / fy), rel=1e-5)
    assert np.all(img[30:] == CFG.max_range)


def test_bad_poses_raise_naming_the_env():
    cam = DepthCamera(CFG, [[Sphere((3.0, 0.0, 0.0), 1.0)]])
    pos, R = np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1))
    pos[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"non-finite.*\[1\]"):
        cam.render(pos, R)
    R2 = R.copy()
    R2[2] *= 2.0
    with pytest.raises(ValueError, match=r"not a rotation.*\[2\]"):
        cam.render(np.zeros((3, 3)), R2)
    with pytest.raises(ValueError, match="scene ids out of range"):
        cam.render(np.zeros((3, 3)), R, scene_ids=[0, 1, 0])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        cam.render(np.zeros((3, 2)), R)


def test_config_is_strict_and_validated():
    cfg = load_config(CameraConfig, overrides=["mount_pitch_deg=12.5", "max_range=8"])
    assert cfg.mount_pitch_deg == 12.5 and cfg.max_range == 8.0
    with pytest.raises(ConfigError, match="hfov"):
        load_config(CameraConfig, overrides=["hfov=90"])
    with pytest.raises(ConfigError, match="max_range"):
        load_config(CameraConfig, overrides=["max_range=0.1"])


# ----------------------------------------------------------------------------- normalisation
def test_normalize_depth_hand_values():
    z = np.array([0.2, 2.0, 10.0, 20.0, 0.0, np.nan], dtype=np.float32)
    # inverse: 0.2 / z -> 1, 0.1, 0.02, 0.02 (clipped at max range); invalid -> 0
    assert np.allclose(normalize_depth(z, CFG), [1.0, 0.1, 0.02, 0.02, 0.0, 0.0])
    lin = CameraConfig(normalization="linear")
    # linear: z / 10 -> 0.02, 0.2, 1, 1; invalid -> 0
    assert np.allclose(normalize_depth(z, lin), [0.02, 0.2, 1.0, 1.0, 0.0, 0.0])


# ----------------------------------------------------------------------------- point cloud
def test_points_lie_on_surfaces():
    scene = make_scene("ablation", 2)
    cfg = CameraConfig(mount_pitch_deg=15.0)
    rng = np.random.default_rng(5)
    pos_w, R_wb = _free_poses(scene, 4, rng)
    pos_w[:, 0] = np.clip(pos_w[:, 0], 5, 55)  # inside the xy bounds, so the floor is seen
    pos_w[:, 1] = np.clip(pos_w[:, 1], -10, 10)
    imgs = DepthCamera(cfg, [scene]).render(pos_w, R_wb)
    floor = Box((32.0, 0.0, -0.05), (32.0, 16.0, 0.05))
    for i in range(len(pos_w)):
        pts = depth_to_points(imgs[i, 0], pos_w[i], R_wb[i], cfg)
        valid = (imgs[i, 0] > cfg.min_range) & (imgs[i, 0] < cfg.max_range)
        assert pts.shape[0] >= valid.sum() > 100
        # Every point not clamped at min range is on a surface: ESDF ~ 0 (float32 depth: ~1e-6 relative).
        o_w, _ = camera_poses(cfg, pos_w[i], R_wb[i])
        far = np.linalg.norm(pts - o_w, axis=1) > cfg.min_range * 1.8
        sdf = union_sdf((*scene.primitives, floor), pts[far])
        assert np.abs(sdf).max() < 1e-4


def test_points_drop_invalid_pixels_and_voxels_average():
    cfg = CameraConfig(mount_pos_b=[0.0, 0.0, 0.0])
    depth = np.full((60, 100), 4.0, dtype=np.float32)
    depth[0, :] = 0.0  # invalid
    depth[1, :] = cfg.max_range  # no return
    depth[2, :] = np.nan
    pts = depth_to_points(depth, np.zeros(3), np.eye(3), cfg)
    assert pts.shape == (57 * 100, 3)
    assert np.allclose(pts[:, 0], 4.0)  # z-depth 4 along body x: the plane x = 4
    vox = depth_to_points(depth, np.zeros(3), np.eye(3), cfg, voxel=0.5)
    keys = np.floor(pts / 0.5).astype(int)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    assert vox.shape == (len(uniq), 3)
    centroids = np.array([pts[inv.ravel() == j].mean(axis=0) for j in range(len(uniq))])
    order = np.lexsort(np.floor(vox / 0.5).T[::-1])
    assert np.allclose(vox[order], centroids)
    assert voxel_downsample(np.zeros((0, 3)), 0.1).shape == (0, 3)
    # A caller's buffer: the same points, written to its head, the rows after them untouched.
    buf = np.full((6000 + 10, 3), 7.0)
    into = depth_to_points(depth, np.zeros(3), np.eye(3), cfg, out=buf)
    assert np.shares_memory(into, buf) and np.array_equal(into, pts) and np.all(buf[len(pts) :] == 7.0)
    with pytest.raises(ValueError, match="out must be"):
        depth_to_points(depth, np.zeros(3), np.eye(3), cfg, out=np.empty((100, 3)))
    with pytest.raises(ValueError, match="out must be"):
        depth_to_points(depth, np.zeros(3), np.eye(3), cfg, voxel=0.5, out=buf)


def test_key_slots_number_keys_in_first_seen_order():
    # Keys 7, 7, 3, 9, 3, 7 (a repeat right after itself, and repeats later): slots 0, 0, 1, 2, 1, 0; 3 distinct.
    slots, m = key_slots(np.array([7, 7, 3, 9, 3, 7], dtype=np.int64))
    assert slots.tolist() == [0, 0, 1, 2, 1, 0] and m == 3
    empty, m0 = key_slots(np.zeros(0, dtype=np.int64))
    assert empty.shape == (0,) and m0 == 0
    # Many keys that collide in the table's low bits: each distinct key still gets its own slot, in order.
    keys = np.repeat(np.arange(500, dtype=np.int64) << 42, 3)[::-1].copy()
    slots, m = key_slots(keys)
    assert m == 500 and slots.tolist() == np.repeat(np.arange(500), 3).tolist()


def test_voxel_keys_pack_cube_indices_by_hand():
    # Cube indices floor(p / 0.1) written out: (0, 0, 0) twice, (-1, 0, 0), (1, 0, 0), (0, 0, -3).
    pts = np.array([[0.05, 0.05, 0.05], [0.09, 0.01, 0.0], [-0.01, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, -0.25]])
    lim = 2**20

    def key(ix, iy, iz):
        return (ix + lim) * 2**42 + (iy + lim) * 2**21 + (iz + lim)

    assert voxel_keys(pts, 0.1).tolist() == [key(0, 0, 0), key(0, 0, 0), key(-1, 0, 0), key(1, 0, 0), key(0, 0, -3)]
    assert voxel_keys(np.zeros((0, 3)), 0.1).shape == (0,)
    # Downsampling groups by the same keys: one centroid per distinct key, in first-seen order.
    assert np.allclose(voxel_downsample(pts, 0.1)[0], pts[:2].mean(axis=0))
    assert len(voxel_downsample(pts, 0.1)) == 4
    with pytest.raises(ValueError, match="beyond"):
        voxel_keys(np.array([[0.0, 2.0**20 * 0.1 + 1.0, 0.0]]), 0.1)


# ----------------------------------------------------------------------------- PNG helpers
def test_png_helpers_write_images(tmp_path):
    import matplotlib.image

    depth = np.linspace(0.0, 12.0, 6000, dtype=np.float32).reshape(60, 100)
    save_depth_png(tmp_path / "one.png", depth, CFG, scale=2)
    save_depth_strip(tmp_path / "strip.png", [depth, depth[::-1]], CFG, scale=1, gap=2)
    assert matplotlib.image.imread(tmp_path / "one.png").shape[:2] == (120, 200)
    img = matplotlib.image.imread(tmp_path / "strip.png")
    assert img.shape[:2] == (60, 202)
    assert np.all(img[0, 0, :3] == 0.0)  # the invalid pixel (depth 0) is black


def test_min_pool_equals_the_nearest_depth_of_every_block():
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.1, 10.0, size=(3, 1, 12, 20)).astype(np.float32)
    depth[1, 0, 5, 7] = np.nan  # block (row 5 // 4 = 1, col 7 // 5 = 1) of env 1
    got = min_pool(depth, 3, 4)
    assert got.shape == (3, 3, 4)
    for n in range(3):
        for i in range(3):
            for j in range(4):
                block = depth[n, 0, 4 * i : 4 * i + 4, 5 * j : 5 * j + 5]
                if n == 1 and (i, j) == (1, 1):
                    assert np.isnan(got[n, i, j])
                else:
                    assert got[n, i, j] == block.min()
    with pytest.raises(ValueError, match="3 x 7 pool does not divide 12 x 20"):
        min_pool(depth, 3, 7)
