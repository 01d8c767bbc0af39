"""Voxel grid, occupancy and signed Euclidean distance field (ESDF) of a scene.

Grid: nodes at ``origin + (i, j, k) * res`` for ``i < nx`` etc., covering the scene bounds (node-centred, so
the first and last nodes sit on the bounds). Values are *samples at nodes*; lookups interpolate trilinearly.

ESDF construction (obstacles only, then floor/ceiling):

1. **Exact narrow band.** For each primitive, evaluate its analytic SDF (:mod:`envs.scenes.sdf`) on the nodes
   of its bounding box grown by ``band`` and keep the minimum over primitives. A node whose minimum is
   ``<= band`` has its exact value: any primitive whose grown box misses the node is farther than ``band``.
2. **Far field.** Seeds ``S`` = nodes with ``sdf <= res * sqrt(3) / 2``; every surface point has a seed within
   half a voxel diagonal, so thin poles are never lost. With ``y*`` the nearest seed (scipy's exact EDT with
   its feature transform), ``d(x) ~= |x - y*| + sdf(y*)``. This is an upper bound of the true distance
   (``d`` is 1-Lipschitz) and exceeds it by at most ``res * sqrt(3)`` (in practice a small fraction of a voxel).
3. **Floor and ceiling** are half-spaces: ``d = min(d, z - z_lo)`` and ``d = min(d, z_hi - z)``; exact.

Inside obstacles the value is ``-(depth into the deepest single primitive)``, exact for a lone primitive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from envs.scenes.scene import Scene
from envs.scenes.sdf import primitive_sdf

NO_OBSTACLE_DISTANCE = 1000.0
"""ESDF value (m) used where a scene has no obstacle at all (finite, far beyond any scene)."""


@dataclass(frozen=True)
class Grid:
    """A node-centred regular grid.

    Attributes:
        origin: World position (3,) of node (0, 0, 0), metres (the scene's ``bounds_lo``).
        res: Node spacing in metres.
        shape: Number of nodes per axis ``(nx, ny, nz)``; at least 2 each.
    """

    origin: tuple[float, float, float]
    res: float
    shape: tuple[int, int, int]

    @staticmethod
    def for_scene(scene: Scene, res: float) -> Grid:
        """The grid covering ``scene``'s bounds at spacing ``res`` (the last node is on or just past ``hi``)."""
        if not (math.isfinite(res) and res > 0):
            raise ValueError(f"field resolution must be a positive number of metres, got {res}")
        ext = scene.size
        # ceil(extent / res - eps) intervals -> that + 1 nodes; eps absorbs float error (64 / 0.1 = 640.0000001).
        shape = tuple(max(2, int(math.ceil(e / res - 1e-6)) + 1) for e in ext)
        return Grid(scene.bounds_lo, float(res), shape)  # type: ignore[arg-type]

    def axis(self, k: int) -> np.ndarray:
        """Node coordinates (n_k,) along axis ``k``."""
        return self.origin[k] + self.res * np.arange(self.shape[k])

    def index_box(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice, slice]:
        """Slices of the nodes inside the world box ``[lo, hi]`` (clipped to the grid)."""
        out = []
        for k in range(3):
            a = max(0, int(math.ceil((lo[k] - self.origin[k]) / self.res - 1e-9)))
            b = min(self.shape[k] - 1, int(math.floor((hi[k] - self.origin[k]) / self.res + 1e-9)))
            out.append(slice(a, max(a, b + 1)))
        return tuple(out)  # type: ignore[return-value]

    def points(self, box: tuple[slice, slice, slice]) -> np.ndarray:
        """World coordinates (M, 3) of the nodes in ``box`` (C order: x slowest, z fastest)."""
        axes = [self.axis(k)[box[k]] for k in range(3)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=1)


def obstacle_esdf(scene: Scene, grid: Grid, band_voxels: float = 3.0) -> np.ndarray:
    """Signed distance (nx, ny, nz) float32 to the static primitives only (no floor/ceiling), metres.

    Args:
        scene: The scene.
        grid: Its grid (:meth:`Grid.for_scene`).
        band_voxels: Width of the exact band, in voxels.
    """
    res = grid.res
    band = band_voxels * res
    sdf = np.full(grid.shape, np.inf, dtype=np.float64)
    for prim in scene.primitives:
        lo, hi = prim.aabb()
        box = grid.index_box(lo - band, hi + band)
        if any(s.stop <= s.start for s in box):
            continue
        vals = primitive_sdf(prim, grid.points(box)).reshape([s.stop - s.start for s in box])
        np.minimum(sdf[box], vals, out=sdf[box])
    seeds = sdf <= res * math.sqrt(3.0) / 2.0
    if not seeds.any():
        return np.full(grid.shape, NO_OBSTACLE_DISTANCE, dtype=np.float32)
    # Far field: distance to the nearest seed node plus that seed's own (small, exact) distance.
    dist, idx = ndimage.distance_transform_edt(~seeds, sampling=res, return_indices=True)
    far = dist + sdf[idx[0], idx[1], idx[2]]
    del idx
    out = np.where(sdf <= band, sdf, np.minimum(far, sdf))
    return out.astype(np.float32)


def add_floor_ceiling(scene: Scene, grid: Grid, esdf: np.ndarray) -> np.ndarray:
    """``min(esdf, z - z_lo)`` with a floor and ``min(., z_hi - z)`` with a ceiling (exact half-spaces)."""
    z = grid.axis(2).astype(np.float32)[None, None, :]
    out = esdf
    if scene.floor:
        out = np.minimum(out, z - np.float32(scene.bounds_lo[2]))
    if scene.ceiling:
        out = np.minimum(out, np.float32(scene.bounds_hi[2]) - z)
    return np.ascontiguousarray(out, dtype=np.float32)


def esdf_gradient(esdf: np.ndarray, res: float) -> np.ndarray:
    """Gradient (nx, ny, nz, 3) float32 of the ESDF by central differences (one-sided at the grid faces).

    ``grad_k[i] = (d[i+1] - d[i-1]) / (2 res)`` inside, ``(d[1] - d[0]) / res`` at a face. Unit length
    away from medial axes and obstacle surfaces; shorter where two fronts meet (a true kink).
    """
    g = np.empty((*esdf.shape, 3), dtype=np.float32)
    for k, gk in enumerate(np.gradient(esdf, res)):
        g[..., k] = gk
    return g
