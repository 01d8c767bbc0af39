"""``DepthCamera``: batched exact z-depth rendering of N cameras, each in one of several scenes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from envs.camera import _raycast as rc
from envs.camera.config import CameraConfig
from envs.camera.model import camera_poses, intrinsics, ray_grid
from envs.scenes.primitives import Box, Capsule, Cylinder, Sphere
from envs.scenes.scene import SLAB_THICKNESS

SERIAL_BELOW = 4
"""Batches smaller than this render on the calling thread (no thread-pool wake-up)."""

SceneLike = Any
"""A ``envs.scenes.Scene`` or a sequence of primitives (``Sphere``, ``Cylinder``, ``Capsule``, ``Box``)."""


def _pack_primitive(prim: object) -> tuple[int, np.ndarray, np.ndarray]:
    """Kind code, parameter row (PARAM_WIDTH,) and bounding sphere (4,) of one primitive (see ``_raycast``)."""
    p = np.zeros(rc.PARAM_WIDTH)
    if isinstance(prim, Sphere):
        p[:3], p[3] = prim.center, prim.radius
        return rc.SPHERE, p, np.array([*prim.center, prim.radius])
    if isinstance(prim, (Cylinder, Capsule)):
        p0, p1 = np.array(prim.p0), np.array(prim.p1)
        length = float(np.linalg.norm(p1 - p0))
        p[:3], p[3:6], p[6], p[7] = p0, (p1 - p0) / length, length, prim.radius
        if isinstance(prim, Cylinder):
            # Sphere around the capped cylinder: half-diagonal of its axial section.
            r = float(np.hypot(0.5 * length, prim.radius))
            return rc.CYLINDER, p, np.array([*(0.5 * (p0 + p1)), r])
        return rc.CAPSULE, p, np.array([*(0.5 * (p0 + p1)), 0.5 * length + prim.radius])
    if isinstance(prim, Box):
        p[:3], p[3:6], p[6:15] = prim.center, prim.half, prim.rotation().reshape(-1)
        return rc.BOX, p, np.array([*prim.center, float(np.linalg.norm(prim.half))])
    raise TypeError(f"not a scene primitive: {type(prim).__name__}")


def _scene_parts(scene: SceneLike) -> tuple[list, list]:
    """Static primitives (obstacles, then floor/ceiling slabs) and moving cylinders (at t = 0) of a scene."""
    if hasattr(scene, "primitives"):
        static = list(scene.primitives)
        # Floor and ceiling: the scene's finite slabs of SLAB_THICKNESS, covering the bounds in xy, with inner
        # faces at bounds_lo.z and bounds_hi.z, exactly as Scene.to_mjcf_geoms writes them (docs of envs.scenes).
        lo, hi = np.asarray(scene.bounds_lo, dtype=float), np.asarray(scene.bounds_hi, dtype=float)
        cxy, hxy, t = 0.5 * (lo[:2] + hi[:2]), 0.5 * (hi[:2] - lo[:2]), 0.5 * SLAB_THICKNESS
        if scene.floor:
            static.append(Box((cxy[0], cxy[1], lo[2] - t), (hxy[0], hxy[1], t)))
        if scene.ceiling:
            static.append(Box((cxy[0], cxy[1], hi[2] + t), (hxy[0], hxy[1], t)))
        moving = [m.cylinder for m in scene.moving]
        return static, moving
    return list(scene), []


class DepthCamera:
    """Renders z-depth images for N cameras, each in one of several scenes, by exact ray casting.

    Each scene is packed once into flat arrays; cameras are rendered in parallel by a numba kernel
    (``envs.camera._raycast``). Moving obstacles are vertical cylinders whose base centres are updated with
    :meth:`set_moving_positions` (an O(M) array write, no rebuild).

    Args:
        cfg: Camera model (resolution, field of view, ranges, mount).
        scenes: Scenes (``envs.scenes.Scene``: obstacles, floor/ceiling slabs and moving obstacles at t = 0) or
            plain primitive lists. Camera poses passed to :meth:`render` are in the chosen scene's own frame.
        floor_z: Optional extra infinite floor ``z <= floor_z`` (a half-space) added to every scene; None: none.
    """

    def __init__(self, cfg: CameraConfig, scenes: Sequence[SceneLike], floor_z: float | None = None) -> None:
        if hasattr(scenes, "primitives"):
            scenes = [scenes]  # one Scene
        elif len(scenes) and isinstance(scenes[0], (Sphere, Cylinder, Capsule, Box)):
            scenes = [scenes]  # one flat primitive list
        self.cfg = cfg
        kinds, params, bsph, offsets = [], [], [], [0]
        self._moving_slices: list[slice] = []
        for scene in scenes:
            static, moving = _scene_parts(scene)
            start = len(kinds)
            for prim in [*moving, *static]:  # moving cylinders first: a contiguous, updatable block
                k, p, b = _pack_primitive(prim)
                kinds.append(k)
                params.append(p)
                bsph.append(b)
            if floor_z is not None:
                p = np.zeros(rc.PARAM_WIDTH)
                p[:4] = (0.0, 0.0, 1.0, float(floor_z))  # solid {x : z <= floor_z}
                kinds.append(rc.HALFSPACE)
                params.append(p)
                bsph.append(np.zeros(4))
            self._moving_slices.append(slice(start, start + len(moving)))
            offsets.append(len(kinds))
        self.num_scenes = len(offsets) - 1
        self._kinds = np.asarray(kinds, dtype=np.int64).reshape(-1)
        self._params = np.asarray(params, dtype=np.float64).reshape(-1, rc.PARAM_WIDTH)
        self._bsph = np.asarray(bsph, dtype=np.float64).reshape(-1, 4)
        self._offsets = np.asarray(offsets, dtype=np.int64)
        self._x_u, self._y_v = ray_grid(cfg)
        self._intr = intrinsics(cfg)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Per-camera image shape ``(1, H, W)``."""
        return (1, self.cfg.height, self.cfg.width)

    def num_moving(self, scene_id: int) -> int:
        """Number of moving obstacles in scene ``scene_id``."""
        s = self._moving_slices[scene_id]
        return s.stop - s.start

    def set_moving_positions(self, scene_id: int, base_w: np.ndarray) -> None:
        """Move scene ``scene_id``'s moving cylinders to base centres ``base_w`` (M, 3) (``Scene.moving_positions``).

        Each cylinder keeps its radius, length and vertical axis: ``p0 = base``, ``p1 = base + (0, 0, L)``.
        """
        s = self._moving_slices[scene_id]
        base = np.asarray(base_w, dtype=np.float64).reshape(-1, 3)
        if base.shape[0] != s.stop - s.start:
            raise ValueError(f"scene {scene_id} has {s.stop - s.start} moving obstacles, got {base.shape[0]} positions")
        if not np.all(np.isfinite(base)):
            raise ValueError(f"moving obstacle positions for scene {scene_id} must be finite")
        p = self._params[s]
        p[:, 0:3] = base
        # bounding-sphere centre = axis midpoint = base + (L/2) a
        self._bsph[s, 0:3] = base + 0.5 * p[:, 6:7] * p[:, 3:6]
        self._params[s] = p

    def render(self, pos_w: np.ndarray, R_wb: np.ndarray, scene_ids: np.ndarray | None = None) -> np.ndarray:
        """Render the depth images of N cameras.

        Args:
            pos_w: Body origins (N, 3), metres, each in its scene's frame.
            R_wb: Body-to-world rotations (N, 3, 3).
            scene_ids: Scene index of each camera (N,) ints; None: all in scene 0.

        Returns:
            z-depth (N, 1, H, W) float32 in [min_range, max_range]: ``max_range`` where nothing is hit within
            it, ``min_range`` for surfaces closer than that, and ``min_range`` everywhere for a camera whose
            optical centre is inside an obstacle (the floor and ceiling are slabs: inside counts as inside).

        Raises:
            ValueError: On non-finite or wrongly shaped poses, non-rotation matrices, or bad scene ids,
                naming the offending camera indices.
        """
        pos_w = np.asarray(pos_w, dtype=np.float64)
        R_wb = np.asarray(R_wb, dtype=np.float64)
        if pos_w.ndim == 1:
            pos_w = pos_w[None]
        if R_wb.ndim == 2:
            R_wb = R_wb[None]
        n = pos_w.shape[0]
        if pos_w.shape != (n, 3) or R_wb.shape != (n, 3, 3):
            raise ValueError(f"expected pos_w (N, 3) and R_wb (N, 3, 3), got {pos_w.shape} and {R_wb.shape}")
        finite = np.isfinite(pos_w).all(axis=1) & np.isfinite(R_wb).all(axis=(1, 2))
        if not finite.all():
            raise ValueError(f"non-finite camera pose for env ids {np.flatnonzero(~finite).tolist()}")
        # R^T R = I within 1e-4: anything else would silently shear the rays.
        err = np.abs(np.einsum("nki,nkj->nij", R_wb, R_wb) - np.eye(3)).max(axis=(1, 2)) if n else np.zeros(0)
        if np.any(err > 1e-4):
            raise ValueError(f"R_wb is not a rotation matrix for env ids {np.flatnonzero(err > 1e-4).tolist()}")
        if scene_ids is None:
            sid = np.zeros(n, dtype=np.int64)
        else:
            sid = np.asarray(scene_ids, dtype=np.int64).reshape(-1)
            if sid.shape != (n,):
                raise ValueError(f"scene_ids must have shape ({n},), got {np.shape(scene_ids)}")
            bad = (sid < 0) | (sid >= self.num_scenes)
            if bad.any():
                raise ValueError(f"scene ids out of range [0, {self.num_scenes}) for env ids {np.flatnonzero(bad)}")
        o_w, R_wc = camera_poses(self.cfg, pos_w, R_wb)
        out = np.empty((n, self.cfg.height, self.cfg.width), dtype=np.float32)
        fx, fy, cx, cy = self._intr
        kernel = rc.render_batch if n >= SERIAL_BELOW else rc.render_batch_serial
        kernel(
            o_w, np.ascontiguousarray(R_wc), sid, self._offsets, self._kinds, self._params, self._bsph,
            self._x_u, self._y_v, fx, fy, cx, cy, float(self.cfg.min_range), float(self.cfg.max_range), out,
        )  # fmt: skip
        return out[:, None]
