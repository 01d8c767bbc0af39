"""Geodesic fields to goal *points* (anchors) rather than to the whole goal region.

The scene's field ``Phi`` flows to the nearest point of the 1 x 32 x 2 m goal region, but an episode succeeds only
within 5 m of its own sampled goal. Progress along the region field therefore rewards flying straight down the
course and never towards the goal's side of it, which is the wrong incentive for the last few metres. Computing
a Dijkstra field per episode is too slow (seconds per reset), so each scene gets ``K`` anchor goals spread across
the goal region (``y`` evenly spaced, ``x`` and ``z`` at the region's centre), each with its own geodesic field;
training episodes draw their goal among the anchors and are rewarded with that anchor's field.

Memory: one float32 field per anchor (a 64 x 32 x 3 m scene at 0.2 m has 0.83 M nodes: 3.3 MB per anchor).
Fields are cached on disk next to the scene fields (same cache directory), one file per anchor, keyed by the scene
fields' key and the anchor's position. With ``lazy=True`` an anchor's field is built (or read) on the first lookup
that needs it, so a fresh env pays only for the goals it draws.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from envs.fields.build import DEFAULT_STENCIL, SceneFields, cache_key, default_cache_dir, region_mask, report
from envs.fields.geodesic import geodesic_field, nearest_traversable
from envs.fields.lookup import FieldStack, trilinear_batch


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
        fields: The scenes' fields: a :class:`envs.fields.FieldStack` (lazy or not) or a sequence of
            :class:`SceneFields` (grid, ESDF and vehicle radius are reused).
        count: Anchors per scene, K.
        stencil: Dijkstra stencil (as :func:`envs.fields.build_fields`).
        cache_dir: Cache directory (default: the scene-field cache).
        half_size: Half extent (m) in y and z of the small box of goal nodes around each anchor.
        lazy: Build (or read from the cache) an anchor's field on the first lookup that needs it, and a scene's
            anchor validity on the first draw in that scene; otherwise everything is built now.
        clearance_cost: ``(d_ref, weight)``, or None: the Dijkstra then weighs each metre by
            ``1 + weight * max(0, d_ref - d) / d_ref`` (``d`` the ESDF, mean of an edge's end nodes), so shortest
            paths keep to the middle of corridors narrower than ``2 d_ref`` and Phi is a weighted length, not metres.
        height_cost: ``(h_ref, weight)``, or None: each metre weighs ``weight * max(0, z - h_ref)`` more (``z`` the
            node's height above the scene's floor ``bounds_lo.z``, in metres; with ``clearance_cost`` the two add),
            so shortest paths keep low where a low way is not much longer.

    Raises:
        ValueError: ``count < 1``, a bad ``clearance_cost``, or a scene whose every anchor is blocked (when that
            scene is first used).
    """

    def __init__(
        self,
        scenes: Sequence[object],
        fields: FieldStack | Sequence[SceneFields],
        count: int,
        stencil: str = DEFAULT_STENCIL,
        cache_dir: str | os.PathLike | None = None,
        half_size: float = 0.5,
        lazy: bool = False,
        clearance_cost: tuple[float, float] | None = None,
        height_cost: tuple[float, float] | None = None,
    ) -> None:
        if count < 1:
            raise ValueError(f"anchor count must be >= 1, got {count}")
        if clearance_cost is not None and not (len(clearance_cost) == 2 and clearance_cost[0] > 0
                                               and clearance_cost[1] >= 0):  # fmt: skip
            raise ValueError(f"clearance_cost must be (d_ref > 0, weight >= 0), got {clearance_cost}")
        self.clearance_cost = None if clearance_cost is None else (float(clearance_cost[0]), float(clearance_cost[1]))
        if height_cost is not None and not (len(height_cost) == 2 and height_cost[0] >= 0 and height_cost[1] >= 0):
            raise ValueError(f"height_cost must be (h_ref >= 0, weight >= 0), got {height_cost}")
        self.height_cost = None if height_cost is None else (float(height_cost[0]), float(height_cost[1]))
        self.count = count
        self.scenes = list(scenes)
        self.num_scenes = len(self.scenes)
        self.stack = fields if isinstance(fields, FieldStack) else FieldStack(fields)
        if self.stack.num_scenes != self.num_scenes:
            raise ValueError(f"{self.num_scenes} scenes but fields for {self.stack.num_scenes}")
        self._stencil, self._half = stencil, half_size
        self._cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        self.anchors = np.stack([anchor_points(s, count) for s in self.scenes])  # (S, K, 3)
        self.valid = np.ones((self.num_scenes, count), dtype=bool)
        self._known = np.zeros(self.num_scenes, dtype=bool)  # validity computed
        self._ready = np.zeros(self.num_scenes * count, dtype=bool)  # field built, per (scene, anchor)
        nodes = self.stack.shape.prod(axis=1)
        self._shape = np.repeat(self.stack.shape, count, axis=0)  # one "field" per (scene, anchor)
        self._origin = np.repeat(self.stack.origin, count, axis=0)
        self._res = np.repeat(self.stack.res, count, axis=0)
        sizes = np.repeat(nodes, count)
        self._offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self._phi = np.zeros(int(sizes.sum()), dtype=np.float32)  # pages mapped only where an anchor is written
        self._empty1, self._empty3 = np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
        if not lazy:
            self._ensure_fields(np.arange(self.num_scenes * count))

    # ------------------------------------------------------------------------------------------------ lazy build
    def _key(self, s: int) -> str:
        f = self.stack.scene_fields(s)
        key = cache_key(self.scenes[s], f.res, f.vehicle_radius, self._stencil)
        if self.clearance_cost is not None:
            key = f"{key}|clearance_cost{list(self.clearance_cost)}"
        return key if self.height_cost is None else f"{key}|height_cost{list(self.height_cost)}"

    def _ensure_valid(self, scene_ids: np.ndarray) -> None:
        """Anchor validity (some goal node of its box is traversable) of every scene in ``scene_ids``."""
        for s in np.unique(np.asarray(scene_ids, dtype=np.int64)[~self._known[scene_ids]]).tolist():
            f = self.stack.scene_fields(s)
            trav = f.esdf > f.vehicle_radius
            self.valid[s] = [(self._goal_mask(s, k) & trav).any() for k in range(self.count)]
            self._known[s] = True
            if not self.valid[s].any():
                raise ValueError(f"scene {s} ({self.scenes[s].family}/{self.scenes[s].index}): every goal anchor "
                                 f"is blocked")  # fmt: skip

    def _goal_mask(self, s: int, k: int) -> np.ndarray:
        glo, ghi = np.asarray(self.scenes[s].goal_region[0]), np.asarray(self.scenes[s].goal_region[1])
        a, h = self.anchors[s, k], self._half
        box = ((glo[0], a[1] - h, a[2] - h), (ghi[0], a[1] + h, a[2] + h))
        return region_mask(self.stack.scene_fields(s).grid, box)

    def _ensure_fields(self, flat_ids: np.ndarray) -> None:
        """Build (or read) the field of every (scene, anchor) in ``flat_ids`` (``s * count + k``) not built yet.

        The Dijkstra solves release the GIL, so the anchors to build run on one thread per core.
        """
        need = np.unique(flat_ids[~self._ready[flat_ids]])
        jobs = []
        for s in np.unique(need // self.count).tolist():
            self._ensure_valid(np.array([s]))
            todo = self._load(s, [int(k) for k in need[need // self.count == s] % self.count])
            if todo:
                f = self.stack.scene_fields(s)
                trav = f.esdf > f.vehicle_radius
                fill = nearest_traversable(trav, f.res)  # depends on the grid only: shared by the scene's anchors
                cost = None  # likewise
                if self.clearance_cost is not None:
                    d_ref, weight = self.clearance_cost
                    cost = 1.0 + weight * np.clip(d_ref - f.esdf, 0.0, d_ref) / d_ref
                if self.height_cost is not None:
                    h_ref, weight = self.height_cost
                    z = f.res * np.arange(f.shape[2], dtype=np.float64)  # above the floor (origin = bounds_lo)
                    cost = (1.0 if cost is None else cost) + weight * np.maximum(z - h_ref, 0.0)[None, None, :]
                    cost = np.broadcast_to(cost, f.shape)
                jobs += [(s, k, trav, fill, cost) for k in todo]
        if not jobs:
            return
        names = sorted({f"{self.scenes[s].family}/{self.scenes[s].index}" for s, *_ in jobs})
        t0 = time.perf_counter()
        report(f"{', '.join(names)}: building {len(jobs)} goal-anchor field(s) (cold cache) ...")

        def solve(job: tuple) -> tuple[int, int, np.ndarray]:
            s, k, trav, fill, cost = job
            f = self.stack.scene_fields(s)
            if not self.valid[s, k]:
                return s, k, np.zeros(f.shape, np.float32)
            diag = float(np.linalg.norm(np.subtract(self.scenes[s].bounds_hi, self.scenes[s].bounds_lo)))
            return s, k, geodesic_field(trav, self._goal_mask(s, k), f.res, diag, self._stencil, fill, cost)[0]

        workers = min(len(jobs), os.cpu_count() or 1)
        with ThreadPoolExecutor(workers) as pool:
            for done, (s, k, phi) in enumerate(pool.map(solve, jobs), 1):
                self._store(s, k, phi)
                self._save(s, k, phi)
                report(f"{', '.join(names)}: goal-anchor fields {done}/{len(jobs)} (cold cache) ...")
        report(f"{', '.join(names)}: {len(jobs)} goal-anchor field(s) built in {time.perf_counter() - t0:.1f} s "
               f"on {workers} thread(s)", True)  # fmt: skip

    def _store(self, s: int, k: int, phi: np.ndarray) -> None:
        i = s * self.count + k
        lo = int(self._offset[i])
        self._phi[lo : lo + phi.size] = phi.reshape(-1)
        self._ready[i] = True

    def _file(self, s: int, k: int) -> Path:
        tag = f"{self._key(s)}|{self._half}|{self.anchors[s, k].tolist()}"
        return self._cache / f"anchor_{hashlib.sha256(tag.encode()).hexdigest()[:40]}.npz"

    def _load(self, s: int, ks: list[int]) -> list[int]:
        """Read the cached fields of anchors ``ks`` of scene ``s``; returns those still to build.

        The one-file-per-scene layout of earlier versions is read too.
        """
        legacy = f"{self._key(s)}|{self.count}|{self._half}|{self.anchors[s].tolist()}"
        old = self._cache / f"anchors_{hashlib.sha256(legacy.encode()).hexdigest()[:40]}.npz"
        if old.is_file():
            with np.load(old) as z:
                phi = z["phi"]
            for k in range(self.count):
                if not self._ready[s * self.count + k]:
                    self._store(s, k, phi[k])
            return []
        todo = []
        for k in ks:
            file = self._file(s, k)
            if file.is_file():
                with np.load(file) as z:
                    self._store(s, k, z["phi"])
            else:
                todo.append(k)
        return todo

    def _save(self, s: int, k: int, phi: np.ndarray) -> None:
        self._cache.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self._cache, suffix=".npz")
        os.close(fd)
        try:
            np.savez(tmp, phi=phi)
            os.replace(tmp, self._file(s, k))  # atomic: concurrent builders never read a partial file
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    # ------------------------------------------------------------------------------------------------ queries
    def sample(self, scene_ids: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A uniformly drawn valid anchor index per scene id (M,)."""
        scene_ids = np.asarray(scene_ids, dtype=np.int64)
        self._ensure_valid(scene_ids)
        out = np.empty(len(scene_ids), dtype=np.int64)
        for s in np.unique(scene_ids):
            sel = np.flatnonzero(scene_ids == s)
            out[sel] = rng.choice(np.flatnonzero(self.valid[s]), len(sel))
        return out

    def nearest(self, scene_ids: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """The valid anchor closest to each goal (M, 3) -> (M,) (for goals pinned by the caller)."""
        scene_ids = np.asarray(scene_ids, dtype=np.int64)
        self._ensure_valid(scene_ids)
        d = np.linalg.norm(self.anchors[scene_ids] - goals[:, None, :], axis=2)
        d[~self.valid[scene_ids]] = np.inf
        return np.argmin(d, axis=1)

    def kernel_fields(self, scene_ids: np.ndarray, anchor_ids: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(index (N,), offset, shape, origin, res, esdf, grad, phi)`` for ``trilinear_point`` in a kernel.

        Builds the (scene, anchor) fields named first; ``index`` is each entry's field, ``esdf`` and ``grad`` are
        empty (these fields hold Phi only).
        """
        ids = (np.asarray(scene_ids, dtype=np.int64) * self.count + np.asarray(anchor_ids, dtype=np.int64)).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= self._ready.size):
            raise ValueError(f"(scene, anchor) pair out of range: {self.num_scenes} scenes x {self.count} anchors")
        if not self._ready[ids].all():
            self._ensure_fields(ids)
        return ids, self._offset, self._shape, self._origin, self._res, self._empty1, self._empty3, self._phi

    def geodesic(self, scene_ids: np.ndarray, anchor_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Phi of each point (N, 3) to its env's anchor goal (N,), metres; outside the grid Phi grows."""
        ids = (np.asarray(scene_ids, dtype=np.int64) * self.count + np.asarray(anchor_ids, dtype=np.int64)).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= self._ready.size):
            raise ValueError(f"(scene, anchor) pair out of range: {self.num_scenes} scenes x {self.count} anchors")
        if not self._ready[ids].all():  # per-step path: one gather when every field asked for is built
            self._ensure_fields(ids)
        pts = np.ascontiguousarray(points, dtype=np.float64)
        out = np.empty(len(ids))
        trilinear_batch(
            ids, pts, self._offset, self._shape, self._origin, self._res, self._empty1, self._empty3, self._phi,
            False, False, True, self._empty1, self._empty3, out,
        )  # fmt: skip
        return out
