"""Geodesic fields to goal *points* (anchors) rather than to the whole goal region.

The scene's field ``Phi`` flows to the nearest point of the 1 x 32 x 2 m goal region, but an episode succeeds only
within 5 m of its own sampled goal. Progress along the region field therefore rewards flying straight down the
course and never towards the goal's side of it, which is the wrong incentive for the last few metres. Computing
a Dijkstra field per episode is too slow (seconds per reset), so each scene gets ``K`` anchor goals spread across
the goal region (``y`` evenly spaced, ``x`` and ``z`` at the region's centre), each with its own geodesic field;
training episodes draw their goal among the anchors and are rewarded with that anchor's field.

Memory: one float32 field per anchor (a 64 x 32 x 3 m scene at 0.2 m has 0.83 M nodes: 3.3 MB per anchor).
Fields are cached on disk next to the scene fields (same cache directory), keyed by the scene fields' key and the
anchor layout.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from envs.fields.build import DEFAULT_STENCIL, SceneFields, cache_key, default_cache_dir, region_mask
from envs.fields.geodesic import geodesic_field
from envs.fields.lookup import _trilinear


def anchor_points(scene: object, count: int, edge_margin: float = 1.5) -> np.ndarray:
    """(count, 3) anchor goals: y evenly spaced across the goal region (``edge_margin`` in from its sides)."""
    lo, hi = np.asarray(scene.goal_region[0], dtype=float), np.asarray(scene.goal_region[1], dtype=float)
    c = 0.5 * (lo + hi)
    ys = np.linspace(lo[1] + edge_margin, hi[1] - edge_margin, count) if count > 1 else np.array([c[1]])
    return np.stack((np.full(count, c[0]), ys, np.full(count, c[2])), axis=1)


class GoalAnchorFields:
    """Geodesic fields ``Phi_{s,k}`` to anchor ``k`` of scene ``s``, with batched trilinear lookups.

    Args:
        scenes: The scenes (their ``goal_region`` defines the anchors).
        fields: Each scene's :class:`SceneFields` (grid, ESDF and vehicle radius are reused).
        count: Anchors per scene, K.
        stencil: Dijkstra stencil (as :func:`envs.fields.build_fields`).
        cache_dir: Cache directory (default: the scene-field cache).
        half_size: Half extent (m) in y and z of the small box of goal nodes around each anchor.
    """

    def __init__(
        self,
        scenes: Sequence[object],
        fields: Sequence[SceneFields],
        count: int,
        stencil: str = DEFAULT_STENCIL,
        cache_dir: str | os.PathLike | None = None,
        half_size: float = 0.5,
    ) -> None:
        if count < 1:
            raise ValueError(f"anchor count must be >= 1, got {count}")
        self.count = count
        self.num_scenes = len(scenes)
        cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        self.anchors = np.stack([anchor_points(s, count) for s in scenes])  # (S, K, 3)
        phis, self.valid = [], np.ones((self.num_scenes, count), dtype=bool)
        for s, (scene, f) in enumerate(zip(scenes, fields, strict=True)):
            key = cache_key(scene, f.res, f.vehicle_radius, stencil)
            tag = hashlib.sha256(f"{key}|{count}|{half_size}|{self.anchors[s].tolist()}".encode()).hexdigest()[:40]
            file = cache / f"anchors_{tag}.npz"
            if file.is_file():
                with np.load(file) as z:
                    phi, valid = z["phi"], z["valid"]
            else:
                phi, valid = self._build(scene, f, self.anchors[s], stencil, half_size)
                cache.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=cache, suffix=".npz")
                os.close(fd)
                np.savez(tmp, phi=phi, valid=valid)
                os.replace(tmp, file)  # atomic: concurrent builders never read a partial file
            phis.append(phi)
            self.valid[s] = valid
        if not self.valid.any(axis=1).all():
            bad = np.flatnonzero(~self.valid.any(axis=1)).tolist()
            raise ValueError(f"scenes {bad}: every goal anchor is blocked")
        shape = np.array([f.shape for f in fields], dtype=np.int64)
        nodes = shape.prod(axis=1)
        self._shape = np.repeat(shape, count, axis=0)  # one "field" per (scene, anchor)
        self._origin = np.repeat(np.array([f.origin for f in fields], dtype=np.float64), count, axis=0)
        self._res = np.repeat(np.array([f.res for f in fields], dtype=np.float64), count, axis=0)
        sizes = np.repeat(nodes, count)
        self._offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self._phi = np.concatenate([p.reshape(-1) for p in phis]).astype(np.float32, copy=False)
        self._empty1, self._empty3 = np.zeros(0, np.float32), np.zeros((0, 3), np.float32)

    @staticmethod
    def _build(scene: object, f: SceneFields, anchors: np.ndarray, stencil: str, half: float) -> tuple:
        trav = f.esdf > f.vehicle_radius
        diag = float(np.linalg.norm(np.subtract(scene.bounds_hi, scene.bounds_lo)))
        glo, ghi = np.asarray(scene.goal_region[0]), np.asarray(scene.goal_region[1])
        phi = np.empty((len(anchors), *f.shape), dtype=np.float32)
        valid = np.ones(len(anchors), dtype=bool)
        for k, a in enumerate(anchors):
            box = ((glo[0], a[1] - half, a[2] - half), (ghi[0], a[1] + half, a[2] + half))
            mask = region_mask(f.grid, box)
            if not (mask & trav).any():
                valid[k] = False
                phi[k] = 0.0
                continue
            phi[k] = geodesic_field(trav, mask, f.res, diag, stencil)[0]
        return phi, valid

    def sample(self, scene_ids: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A uniformly drawn valid anchor index per scene id (M,)."""
        out = np.empty(len(scene_ids), dtype=np.int64)
        for s in np.unique(scene_ids):
            sel = np.flatnonzero(scene_ids == s)
            out[sel] = rng.choice(np.flatnonzero(self.valid[s]), len(sel))
        return out

    def nearest(self, scene_ids: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """The valid anchor closest to each goal (M, 3) -> (M,) (for goals pinned by the caller)."""
        d = np.linalg.norm(self.anchors[scene_ids] - goals[:, None, :], axis=2)
        d[~self.valid[scene_ids]] = np.inf
        return np.argmin(d, axis=1)

    def geodesic(self, scene_ids: np.ndarray, anchor_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Phi of each point (N, 3) to its env's anchor goal (N,), metres; outside the grid Phi grows."""
        ids = (np.asarray(scene_ids, dtype=np.int64) * self.count + np.asarray(anchor_ids, dtype=np.int64)).ravel()
        pts = np.ascontiguousarray(points, dtype=np.float64)
        out = np.empty(len(ids))
        _trilinear(
            ids, pts, self._offset, self._shape, self._origin, self._res, self._empty1, self._empty3, self._phi,
            False, False, True, self._empty1, self._empty3, out,
        )  # fmt: skip
        return out
