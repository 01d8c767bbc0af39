"""PNG helpers for depth images: one frame, or a strip of consecutive frames."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from envs.camera.config import CameraConfig


def depth_to_rgb(depth: np.ndarray, cfg: CameraConfig, cmap: str = "turbo") -> np.ndarray:
    """Colour image (H, W, 3) uint8 of one depth image (H, W): near red, far blue; invalid (0 / NaN) black.

    Colours follow inverse depth ``min_range / z`` (the network's default normalisation), which spreads the
    near range where obstacles matter.
    """
    import matplotlib

    z = np.asarray(depth, dtype=np.float64).reshape(np.shape(depth)[-2:])
    valid = np.isfinite(z) & (z > 0.0)
    inv = cfg.min_range / np.clip(np.where(valid, z, cfg.max_range), cfg.min_range, cfg.max_range)
    lo = cfg.min_range / cfg.max_range
    rgb = matplotlib.colormaps[cmap]((inv - lo) / (1.0 - lo))[..., :3]
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
