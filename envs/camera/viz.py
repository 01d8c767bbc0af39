"""PNG helpers for depth images: one frame, or a strip of consecutive frames."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from envs.camera.config import CameraConfig


def depth_to_rgb(depth: np.ndarray, cfg: CameraConfig, cmap: str = "turbo") -> np.ndarray:
    """Colour image (H, W, 3) uint8 of one depth image (H, W): near red, far blue; invalid (0 / NaN) black.

    Colours follow log depth, ``1 - log(z / min_range) / log(max_range / min_range)`` (1 at the minimum range,
    0 at the maximum), which shows near and far structure alike.
    """
    import matplotlib

    z = np.asarray(depth, dtype=np.float64).reshape(np.shape(depth)[-2:])
    valid = np.isfinite(z) & (z > 0.0)
    zc = np.clip(np.where(valid, z, cfg.max_range), cfg.min_range, cfg.max_range)
    level = 1.0 - np.log(zc / cfg.min_range) / np.log(cfg.max_range / cfg.min_range)
    rgb = matplotlib.colormaps[cmap](level)[..., :3]
    rgb[~valid] = 0.0
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def save_depth_png(path: str | os.PathLike, depth: np.ndarray, cfg: CameraConfig, scale: int = 4) -> None:
    """Save one depth image (H, W) (or (1, H, W)) as a PNG, each pixel drawn as ``scale`` x ``scale``."""
    import matplotlib.image

    rgb = depth_to_rgb(depth, cfg)
    matplotlib.image.imsave(os.fspath(path), np.kron(rgb, np.ones((scale, scale, 1), dtype=np.uint8)))


def save_depth_strip(
    path: str | os.PathLike, frames: Sequence[np.ndarray] | np.ndarray, cfg: CameraConfig, scale: int = 3, gap: int = 2
) -> None:
    """Save consecutive depth frames (T, H, W) side by side as one PNG, separated by ``gap`` white pixels."""
    import matplotlib.image

    tiles = [np.kron(depth_to_rgb(f, cfg), np.ones((scale, scale, 1), dtype=np.uint8)) for f in frames]
    if not tiles:
        raise ValueError("save_depth_strip needs at least one frame")
    h = tiles[0].shape[0]
    sep = np.full((h, gap, 3), 255, dtype=np.uint8)
    row = [tiles[0]]
    for t in tiles[1:]:
        row += [sep, t]
    matplotlib.image.imsave(os.fspath(path), np.concatenate(row, axis=1))


def make_figures(out_dir: str | os.PathLike) -> list[str]:
    """Write the figures of ``docs/depth.md``: one clean frame per scene family and a noisy 30 Hz strip.

    Run as ``python -m envs.camera.viz docs/img/depth``. Returns the written paths.
    """
    from scipy.spatial.transform import Rotation

    from envs.camera.config import DepthNoiseConfig
    from envs.camera.noise import DepthNoise
    from envs.camera.renderer import DepthCamera
    from envs.scenes import FAMILIES, make_scene

    os.makedirs(out_dir, exist_ok=True)
    cfg = CameraConfig(mount_pitch_deg=10.0)
    written = []
    R_wb = Rotation.from_euler("ZYX", [0.0, 0.0, 0.0]).as_matrix()[None]
    for family in FAMILIES:
        scene = make_scene(family, FAMILIES[family].size // 2)
        cam = DepthCamera(cfg, [scene])
        if scene.moving:
            cam.set_moving_positions(0, scene.moving_positions(2.0))
        # Body 2 m in front of the clutter, 1.5 m up, looking along the flight direction (+x).
        pos = np.array([[2.0, 0.0, 1.5]])
        path = os.path.join(os.fspath(out_dir), f"{family}.png")
        save_depth_png(path, cam.render(pos, R_wb)[0, 0], cfg)
        written.append(path)
    # Flying at 5 m/s through the benchmark scene; D435-like noise, 30 Hz camera at 100 Hz control, 1 frame late.
    scene = make_scene("benchmark", 6)
    cam = DepthCamera(cfg, [scene])
    noise_cfg = DepthNoiseConfig(
        depth_sigma_coeff=0.01, dropout_prob=0.01, holes_per_frame=0.5, edge_prob=0.3, frame_rate_hz=30.0,
        latency_frames=1, invalid_below_min=True,
    )  # fmt: skip
    noise = DepthNoise(noise_cfg, cfg, 1, control_dt=0.01, rng=np.random.default_rng(0))
    rng = np.random.default_rng(1)
    clean, noisy = [], []
    for k in range(8):
        pos = np.array([[2.0 + 0.05 * k, 0.0, 1.5]])
        img = cam.render(pos, R_wb)
        clean.append(img[0, 0])
        noisy.append(noise.apply(img, rng)[0, 0])
    for name, frames in (("strip_clean.png", clean), ("strip_sensor.png", noisy)):
        path = os.path.join(os.fspath(out_dir), name)
        save_depth_strip(path, frames, cfg)
        written.append(path)
    return written


if __name__ == "__main__":  # python -m envs.camera.viz [OUT_DIR]
    import sys

    for p in make_figures(sys.argv[1] if len(sys.argv) > 1 else "docs/img/depth"):
        print(p)
