"""Pinhole camera geometry: intrinsics, the mount on the body, camera poses, and depth normalisation.

Frames (all right-handed):

- body ``b``: FLU (x forward, y left, z up); ``R_wb`` maps body vectors to world, ``pos_w`` is the body origin.
- camera ``c``: optical frame, x to the image right (u), y to the image bottom (v), z along the optical axis.

With mount pitch ``theta`` (positive = looking down), the optical axis in the body frame is
``Ry(theta) @ [1, 0, 0] = [cos theta, 0, -sin theta]``; image right is body ``-y``; image down is
``Ry(theta) @ [0, 0, -1] = [-sin theta, 0, -cos theta]``.

Pixel ``(v, u)`` has its centre at ``(u + 0.5, v + 0.5)`` and looks along ``d_c = (x_u, y_v, 1)`` with
``x_u = (u + 0.5 - W/2) / fx`` and ``y_v = (v + 0.5 - H/2) / fy``. Because ``d_c`` has unit z, a point at
ray parameter ``t`` has z-depth exactly ``t``: the ray casters return z-depth directly.
"""

from __future__ import annotations

import math

import numpy as np

from envs.camera.config import CameraConfig


def intrinsics(cfg: CameraConfig) -> tuple[float, float, float, float]:
    """Focal lengths and principal point ``(fx, fy, cx, cy)`` in pixels.

    The image edges span the field of view: ``tan(hfov / 2) = (W / 2) / fx`` and likewise for ``fy``.
    """
    fx = 0.5 * cfg.width / math.tan(math.radians(cfg.hfov_deg) / 2.0)
    fy = 0.5 * cfg.height / math.tan(math.radians(cfg.vfov_deg) / 2.0)
    return fx, fy, 0.5 * cfg.width, 0.5 * cfg.height


def ray_grid(cfg: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image coordinates of the pixel centres: ``x_u`` (W,) and ``y_v`` (H,), float64."""
    fx, fy, cx, cy = intrinsics(cfg)
    x_u = (np.arange(cfg.width) + 0.5 - cx) / fx
    y_v = (np.arange(cfg.height) + 0.5 - cy) / fy
    return x_u, y_v


def ray_dirs_c(cfg: CameraConfig) -> np.ndarray:
    """Camera-frame ray directions ``(H, W, 3)`` with unit z component (not unit length)."""
    x_u, y_v = ray_grid(cfg)
    d = np.empty((cfg.height, cfg.width, 3))
    d[..., 0] = x_u[None, :]
    d[..., 1] = y_v[:, None]
    d[..., 2] = 1.0
    return d


def R_bc(cfg: CameraConfig) -> np.ndarray:
    """Rotation (3, 3) from the camera optical frame to the body frame; its columns are the camera axes in body."""
    th = math.radians(cfg.mount_pitch_deg)
    s, c = math.sin(th), math.cos(th)
    return np.array(
        [
            [0.0, -s, c],  # columns: image right = -y_b, image down = [-s, 0, -c], optical axis = [c, 0, -s]
            [-1.0, 0.0, 0.0],
            [0.0, -c, -s],
        ]
    )


def camera_poses(cfg: CameraConfig, pos_w: np.ndarray, R_wb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World pose of each camera: optical centres ``(N, 3)`` and rotations ``R_wc`` ``(N, 3, 3)``.

    ``o_w = pos_w + R_wb @ mount_pos_b`` and ``R_wc = R_wb @ R_bc``.
    """
    pos_w = np.asarray(pos_w, dtype=np.float64).reshape(-1, 3)
    R_wb = np.asarray(R_wb, dtype=np.float64).reshape(-1, 3, 3)
    mount = np.asarray(cfg.mount_pos_b, dtype=np.float64)
    o_w = pos_w + R_wb @ mount
    R_wc = R_wb @ R_bc(cfg)
    return o_w, R_wc


def normalize_depth(depth: np.ndarray, cfg: CameraConfig) -> np.ndarray:
    """Map depth in metres to the network's input range [0, 1]; the single place this is done.

    - ``inverse`` (default): ``n = min_range / clip(z, min_range, max_range)``; 1 at the minimum range,
      ``min_range / max_range`` (0.02 by default) at the maximum. Inverse depth is proportional to stereo
      disparity, so the sensor's ``sigma ~ z^2`` noise becomes roughly constant, and resolution is spent
      near the vehicle where collisions happen.
    - ``linear``: ``n = clip(z, min_range, max_range) / max_range``.

    Invalid pixels (``z <= 0`` or not finite) map to 0 in both modes: "no information", the same value as
    nothing seen in the inverse mode.

    Args:
        depth: Depth in metres, any shape (typically (N, 1, H, W)).
        cfg: The camera configuration (ranges and mode).

    Returns:
        float32 array of the same shape.
    """
    z = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(z) & (z > 0.0)
    zc = np.clip(np.where(valid, z, cfg.max_range), cfg.min_range, cfg.max_range)
    n = np.float32(cfg.min_range) / zc if cfg.normalization == "inverse" else zc / np.float32(cfg.max_range)
    return np.where(valid, n, np.float32(0.0)).astype(np.float32, copy=False)


def min_pool(depth: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Nearest depth of each block of a (rows x cols) grid over images (N, ..., H, W): (N, rows, cols).

    Equal to ``depth.reshape(N, rows, H // rows, cols, W // cols).min(axis=(2, 4))`` (``H`` and ``W`` divisible),
    about five times faster: the rows of each block are reduced first, elementwise over whole contiguous image rows,
    then the short column blocks of the one remaining row. NaN propagates as in ``min``.
    """
    n, (h, w) = depth.shape[0], depth.shape[-2:]
    if h % rows or w % cols:
        raise ValueError(f"a {rows} x {cols} pool does not divide {h} x {w} images")
    v = depth.reshape(n, rows, h // rows, w)
    out = v[:, :, 0].copy()
    for i in range(1, h // rows):
        np.minimum(out, v[:, :, i], out=out)
    return out.reshape(n, rows, cols, w // cols).min(axis=3)
