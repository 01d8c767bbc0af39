"""Depth camera benchmark: exact numba ray casting vs ``mujoco.mj_multiRay`` on the same poses.

``python -m shield_nav.bench depth --json`` renders N = 1, 64, 256 cameras in a dense benchmark scene with the
default camera (100 x 60, 87 x 58 deg, 0.2-10 m, 10 deg down-pitch mount), and the same 256 poses one image
at a time with ``mj_multiRay`` (single thread: it has no batched form). The last line is one JSON object:

- ``images_per_s``: ours at N = 256, all numba threads; ``images_per_s_1thread``: ours at N = 256, one thread;
- ``mj_multiray_images_per_s``: ``mj_multiRay`` images per second (one thread);
- ``speedup`` = images_per_s / mj_multiray_images_per_s; ``speedup_per_core`` uses the one-thread figure;
- ``per_n``: images/s and speedup for each N; ``agree_frac_1cm``: fraction of pixels within 1 cm of mj_multiRay;
- ``first_call_s``: the first render in this process (numba cache load, or compilation on a cold cache);
- ``points_us`` / ``points_voxel_us``: ``depth_to_points`` for one image (without / with 0.1 m voxels);
- ``noise_ms_256``: ``DepthNoise.apply`` for 256 envs with every effect on.

Poses: body origins uniform in the scene's flight volume with at least 0.3 m clearance, yaw within 60 deg of
the flight direction (+x), roll and pitch within 20 deg.
"""

from __future__ import annotations

import time

import numpy as np

from shield_nav.bench import common


def _poses(scene: object, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` body poses (pos_w (n, 3), R_wb (n, 3, 3)) in free space of ``scene``."""
    from scipy.spatial.transform import Rotation

    from envs.scenes.sdf import union_sdf

    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(scene.bounds_lo), np.asarray(scene.bounds_hi)  # type: ignore[attr-defined]
    pts = np.zeros((0, 3))
    while pts.shape[0] < n:
        cand = rng.uniform(lo + [0.0, 0.0, 0.5], hi - [0.0, 0.0, 0.5], (4 * n, 3))
        cand = cand[union_sdf(scene.primitives, cand) > 0.3]  # type: ignore[attr-defined]
        pts = np.concatenate([pts, cand])
    pts = pts[:n]
    deg = np.pi / 180.0
    ypr = np.c_[rng.uniform(-60, 60, n) * deg, rng.uniform(-20, 20, n) * deg, rng.uniform(-20, 20, n) * deg]
    return pts, Rotation.from_euler("ZYX", ypr).as_matrix()


def main(argv: list[str]) -> dict:
    """Run the benchmark; print progress and (with ``--json``) the result as the last line."""
    p = common.parser("depth", __doc__.splitlines()[0])
    p.add_argument("--scene", default="benchmark:11", help="FAMILY:INDEX of the scene (default benchmark:11)")
    p.add_argument("--min-time", type=float, default=1.0, help="seconds per timing (default 1.0)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import mujoco
    import numba

    from envs.camera import CameraConfig, DepthCamera
    from envs.camera.config import DepthNoiseConfig
    from envs.camera.noise import DepthNoise
    from envs.camera.pointcloud import depth_to_points
    from envs.camera.reference import MjDepth
    from envs.scenes import make_scene

    family, index = args.scene.split(":")
    scene = make_scene(family, int(index))
    cfg = CameraConfig(mount_pitch_deg=10.0)
    pos_w, R_wb = _poses(scene, 256, args.seed)

    t0 = time.perf_counter()
    cam = DepthCamera(cfg, [scene])
    ours = cam.render(pos_w[:1], R_wb[:1])
    first_call_s = time.perf_counter() - t0
    print(f"scene {args.scene}: {len(scene.primitives)} primitives; first render {first_call_s:.2f} s")

    ref = MjDepth(cfg, mujoco.MjModel.from_xml_string(scene.to_mjcf()))
    t0 = time.perf_counter()
    mj_img = ref.render(pos_w, R_wb)
    mj_ips = 256 / (time.perf_counter() - t0)
    ours = cam.render(pos_w, R_wb)
    agree = float(np.mean(np.abs(ours - mj_img) <= 0.01))
    print(f"mj_multiRay: {mj_ips:.0f} images/s (1 thread); agreement within 1 cm: {agree:.6f}")

    threads = numba.get_num_threads()
    per_n = {}
    for n in (1, 64, 256):
        sec, _ = common.time_it(lambda n=n: cam.render(pos_w[:n], R_wb[:n]), min_time=args.min_time)
        ips = n / sec
        per_n[str(n)] = {"images_per_s": round(ips, 1), "speedup": round(ips / mj_ips, 2)}
        print(f"N={n:4d}: {ips:9.0f} images/s ({threads} threads), {ips / mj_ips:6.1f}x mj_multiRay")
    numba.set_num_threads(1)
    sec1, _ = common.time_it(lambda: cam.render(pos_w, R_wb), min_time=args.min_time)
    numba.set_num_threads(threads)
    ips1 = 256 / sec1
    print(f"N= 256: {ips1:9.0f} images/s (1 thread), {ips1 / mj_ips:6.1f}x mj_multiRay per core")

    depth0, pos0, R0 = ours[0, 0], pos_w[0], R_wb[0]
    depth_to_points(depth0, pos0, R0, cfg, voxel=0.1)  # warm up
    pts_s, _ = common.time_it(lambda: depth_to_points(depth0, pos0, R0, cfg), min_time=0.3)
    vox_s, _ = common.time_it(lambda: depth_to_points(depth0, pos0, R0, cfg, voxel=0.1), min_time=0.3)

    ncfg = DepthNoiseConfig(
        depth_sigma_coeff=0.005, dropout_prob=0.02, holes_per_frame=1.0, edge_prob=0.3, latency_frames=1
    )
    noise = DepthNoise(ncfg, cfg, 256)
    rng = np.random.default_rng(0)
    noise_s, _ = common.time_it(lambda: noise.apply(ours, rng), min_time=0.3)
    print(f"depth_to_points: {pts_s * 1e6:.1f} us, with 0.1 m voxels {vox_s * 1e6:.1f} us; noise N=256 "
          f"{noise_s * 1e3:.2f} ms")  # fmt: skip

    ips = per_n["256"]["images_per_s"]
    result = {
        "benchmark": "depth",
        "scene": args.scene,
        "num_primitives": len(scene.primitives),
        "images_per_s": ips,
        "mj_multiray_images_per_s": round(mj_ips, 1),
        "speedup": round(ips / mj_ips, 2),
        "images_per_s_1thread": round(ips1, 1),
        "speedup_per_core": round(ips1 / mj_ips, 2),
        "threads": threads,
        "per_n": per_n,
        "agree_frac_1cm": agree,
        "first_call_s": round(first_call_s, 3),
        "points_us": round(pts_s * 1e6, 2),
        "points_voxel_us": round(vox_s * 1e6, 2),
        "noise_ms_256": round(noise_s * 1e3, 3),
        "machine": common.machine(),
    }
    common.emit(result, args.json)
    return result
