"""Depth image -> world-frame point cloud (for the HOCBF shield), with optional voxel downsampling."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from envs.camera.config import CameraConfig
from envs.camera.model import R_bc, ray_grid

_NJIT = {"cache": True, "fastmath": False, "nogil": True}
_FIB = -7046029254386353131  # 0x9E3779B97F4A7C15 as a signed int64
_GRID_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _grid(cfg: CameraConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cached ``(x_u, y_v, R_bc)`` for a camera configuration (keyed by the fields they depend on)."""
    key = (cfg.width, cfg.height, cfg.hfov_deg, cfg.vfov_deg, cfg.mount_pitch_deg)
    hit = _GRID_CACHE.get(key)
    if hit is None:
        x_u, y_v = ray_grid(cfg)
        hit = _GRID_CACHE[key] = (x_u, y_v, R_bc(cfg))
    return hit


@nb.njit(**_NJIT)
def _backproject(
    depth: np.ndarray,
    pos_w: np.ndarray,
    R_wb: np.ndarray,
    mount_b: np.ndarray,
    Rbc: np.ndarray,
    x_u: np.ndarray,
    y_v: np.ndarray,
    zhi: float,
    out: np.ndarray,
) -> int:
    """Write world points of pixels with 0 < z < zhi into ``out`` (H*W, 3); return their count."""
    # Camera pose: o_w = pos_w + R_wb mount_b, R_wc = R_wb R_bc (written out: no BLAS call for 3x3).
    o = np.empty(3)
    R = np.empty((3, 3))
    for i in range(3):
        o[i] = pos_w[i] + R_wb[i, 0] * mount_b[0] + R_wb[i, 1] * mount_b[1] + R_wb[i, 2] * mount_b[2]
        for j in range(3):
            R[i, j] = R_wb[i, 0] * Rbc[0, j] + R_wb[i, 1] * Rbc[1, j] + R_wb[i, 2] * Rbc[2, j]
    H, W = depth.shape
    m = 0
    for v in range(H):
        y = y_v[v]
        for u in range(W):
            z = depth[v, u]
            if not (z > 0.0 and z < zhi):  # also drops NaN
                continue
            # p_c = z (x_u, y_v, 1);  p_w = o_w + R_wc p_c
            xc, yc = z * x_u[u], z * y
            out[m, 0] = o[0] + R[0, 0] * xc + R[0, 1] * yc + R[0, 2] * z
            out[m, 1] = o[1] + R[1, 0] * xc + R[1, 1] * yc + R[1, 2] * z
            out[m, 2] = o[2] + R[2, 0] * xc + R[2, 1] * yc + R[2, 2] * z
            m += 1
    return m


@nb.njit(**_NJIT)
def _voxel_key(x: float, y: float, z: float, inv: float) -> int:
    """The int64 key of the cube ``floor(p * inv)`` holding point ``p``: 21 bits per axis, indices within +-2^20."""
    lim = 1 << 20
    ix, iy, iz = int(math.floor(x * inv)), int(math.floor(y * inv)), int(math.floor(z * inv))
    if not (-lim <= ix < lim and -lim <= iy < lim and -lim <= iz < lim):
        raise ValueError("voxel index beyond +-2^20 (points too far or voxel too small)")
    return ((ix + lim) << 42) | ((iy + lim) << 21) | (iz + lim)


@nb.njit(**_NJIT)
def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key per point (M, 3), equal exactly when two points share a cubic voxel of edge ``voxel`` (m).

    The packing :func:`voxel_downsample` hashes: ``floor(p / voxel)`` per axis, 21 bits each (voxel indices within
    +-2^20: +-10 km at 1 cm voxels; a point beyond raises ``ValueError``).
    """
    inv = 1.0 / voxel
    out = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        out[i] = _voxel_key(points[i, 0], points[i, 1], points[i, 2], inv)
    return out


@nb.njit(**_NJIT)
def key_slots(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """The slot (N,) of each int64 key, numbered 0, 1, ... in first-seen order, and the number of distinct keys.

    An open-addressing hash table (Fibonacci hashing, linear probing); a key equal to the one before it skips the
    lookup (neighbouring pixels often share a voxel). :func:`voxel_downsample` and the shield's local map group
    points by their :func:`voxel_keys` with it.
    """
    n = keys.shape[0]
    size, bits = 1, 0
    while size < 2 * n + 1:
        size *= 2
        bits += 1
    table_keys = np.empty(size, dtype=np.int64)
    table_slot = np.full(size, -1, dtype=np.int64)
    slots = np.empty(n, dtype=np.int64)
    m = 0
    last_key, j = -1, 0  # voxel keys are >= 0
    for i in range(n):
        key = keys[i]
        if key != last_key:
            # Fibonacci hashing: top ``bits`` bits of key * 2^64 / golden ratio (int64 wrap-around intended).
            h = ((key * _FIB) >> (64 - bits)) & (size - 1)
            while table_slot[h] >= 0 and table_keys[h] != key:
                h = (h + 1) & (size - 1)
            if table_slot[h] < 0:
                table_slot[h] = m
                table_keys[h] = key
                m += 1
            j = table_slot[h]
            last_key = key
        slots[i] = j
    return slots, m


@nb.njit(**_NJIT)
def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid of the points (M, 3) in each occupied cubic voxel of edge ``voxel`` (m), in first-seen order.

    Voxel of a point: its :func:`voxel_keys` key (voxel indices within +-2^20: +-10 km at 1 cm voxels), grouped by
    :func:`key_slots`; each centroid sums its points in their order.
    """
    slots, m = key_slots(voxel_keys(points, voxel))
    acc = np.zeros((m, 3))
    cnt = np.zeros(m, dtype=np.int64)
    for i in range(points.shape[0]):
        j = slots[i]
        acc[j, 0] += points[i, 0]
        acc[j, 1] += points[i, 1]
        acc[j, 2] += points[i, 2]
        cnt[j] += 1
    out = np.empty((m, 3))
    for j in range(m):
        out[j, 0], out[j, 1], out[j, 2] = acc[j, 0] / cnt[j], acc[j, 1] / cnt[j], acc[j, 2] / cnt[j]
    return out


def depth_to_points(
    depth: np.ndarray,
    pos_w: np.ndarray,
    R_wb: np.ndarray,
    cfg: CameraConfig,
    voxel: float | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """World-frame points (M, 3) float64 seen in one depth image.

    Pixel (v, u) with depth z maps to ``o_w + R_wc z (x_u, y_v, 1)`` (see ``envs.camera.model``). Invalid
    pixels (``z <= 0`` or NaN) and pixels without a return (``z >= max_range``) are dropped; pixels clamped to
    ``min_range`` are kept (something is at least that close).

    Args:
        depth: Depth (H, W), or (1, H, W) / (1, 1, H, W), metres.
        pos_w: Body origin (3,) in the world frame at the time the image was taken.
        R_wb: Body-to-world rotation (3, 3).
        cfg: The camera configuration the image was rendered with.
        voxel: If given, return one point (the centroid) per occupied voxel of this edge length (m).
        out: Optional float64 buffer (at least H*W rows, 3) the points are written to; the result is then a view of
            its first M rows (no allocation per image; the caller may fill the rows after M). Not with ``voxel``.

    Returns:
        Points (M, 3), float64.
    """
    d = np.asarray(depth)
    if d.shape != (cfg.height, cfg.width):
        d = d.reshape(cfg.height, cfg.width)
    pos = np.asarray(pos_w, dtype=np.float64).reshape(3)
    R = np.asarray(R_wb, dtype=np.float64).reshape(3, 3)
    if not (np.isfinite(pos).all() and np.isfinite(R).all()):
        raise ValueError("depth_to_points: camera pose must be finite")
    x_u, y_v, Rbc = _grid(cfg)
    if out is None:
        out = np.empty((d.size, 3))
    elif voxel is not None or out.dtype != np.float64 or out.ndim != 2 or out.shape[0] < d.size or out.shape[1] != 3:
        raise ValueError(f"out must be a float64 (>= {d.size}, 3) buffer and voxel None, got {out.dtype} {out.shape}")
    mount = np.asarray(cfg.mount_pos_b, dtype=np.float64)
    m = _backproject(d, pos, R, mount, Rbc, x_u, y_v, float(cfg.max_range), out)
    pts = out[:m]
    if voxel is not None:
        if not voxel > 0.0:
            raise ValueError(f"voxel must be > 0, got {voxel}")
        pts = voxel_downsample(pts, float(voxel))
    return pts
