"""Batched trilinear lookups of ESDF, ESDF gradient and geodesic field over many scenes at once.

:class:`FieldStack` packs several scenes' grids into flat arrays and answers ``(scene_ids (N,), points (N, 3))``
queries in one numba-compiled pass (no Python loop over points). Points are in each scene's own frame.

Trilinear interpolation: with fractional node coordinates ``f = (p - origin) / res``, base node
``i0 = floor(f)`` (clipped so that ``i0 + 1`` is a node) and weights ``t = f - i0``, the value is
``sum_{a,b,c in {0,1}} w_a(t_x) w_b(t_y) w_c(t_z) V[i0 + (a, b, c)]`` with ``w_0(t) = 1 - t``, ``w_1(t) = t``.

Outside the grid box (documented clamping): the point is projected onto the box (``q = clip(p)``), values are
read at ``q``, and with ``o = |p - q|`` the distance outside,

* ESDF: ``d(q) - o`` (leaving the flight volume counts as losing clearance, never as gaining it),
* geodesic: ``Phi(q) + o`` (leaving the volume is never progress),
* gradient: the gradient at ``q``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numba
import numpy as np


@numba.njit(cache=True, fastmath=True, inline="always")
def trilinear_point(
    s: int,
    px: float,
    py: float,
    pz: float,
    offset: np.ndarray,
    shape: np.ndarray,
    origin: np.ndarray,
    res: np.ndarray,
    esdf: np.ndarray,
    grad: np.ndarray,
    phi: np.ndarray,
    want_esdf: bool,
    want_grad: bool,
    want_phi: bool,
) -> tuple[float, float, float, float, float]:
    """One point ``(px, py, pz)`` of field ``s``: ``(esdf, grad_x, grad_y, grad_z, phi)`` (0 where not wanted).

    The per-point body of every batched lookup, for numba kernels that walk the fields themselves (the planning
    expert's path trace); the arrays are a :class:`FieldStack`'s (or :class:`GoalAnchorFields`') flat ones, as
    :meth:`FieldStack.kernel_fields` returns them. Outside the grid box: the module docstring's clamping.
    """
    nx, ny, nz = shape[s, 0], shape[s, 1], shape[s, 2]
    r = res[s]
    fx = (px - origin[s, 0]) / r
    fy = (py - origin[s, 1]) / r
    fz = (pz - origin[s, 2]) / r
    # Distance outside the grid box, in voxels per axis, then clamp onto the box.
    ox = min(fx, 0.0) + max(fx - (nx - 1), 0.0)
    oy = min(fy, 0.0) + max(fy - (ny - 1), 0.0)
    oz = min(fz, 0.0) + max(fz - (nz - 1), 0.0)
    outside = np.sqrt(ox * ox + oy * oy + oz * oz) * r
    fx = min(max(fx, 0.0), nx - 1.0)
    fy = min(max(fy, 0.0), ny - 1.0)
    fz = min(max(fz, 0.0), nz - 1.0)
    i0 = min(int(fx), nx - 2)
    j0 = min(int(fy), ny - 2)
    k0 = min(int(fz), nz - 2)
    tx, ty, tz = fx - i0, fy - j0, fz - k0
    sy = nz
    sx = ny * nz
    base = offset[s] + i0 * sx + j0 * sy + k0
    e = 0.0
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    p = 0.0
    for a in range(2):
        wa = tx if a else 1.0 - tx
        for b in range(2):
            wb = ty if b else 1.0 - ty
            for c in range(2):
                w = wa * wb * (tz if c else 1.0 - tz)
                idx = base + a * sx + b * sy + c
                if want_esdf:
                    e += w * esdf[idx]
                if want_grad:
                    g0 += w * grad[idx, 0]
                    g1 += w * grad[idx, 1]
                    g2 += w * grad[idx, 2]
                if want_phi:
                    p += w * phi[idx]
    return e - outside, g0, g1, g2, p + outside


@numba.njit(cache=True, fastmath=True)
def trilinear_batch(
    ids: np.ndarray,
    pts: np.ndarray,
    offset: np.ndarray,
    shape: np.ndarray,
    origin: np.ndarray,
    res: np.ndarray,
    esdf: np.ndarray,
    grad: np.ndarray,
    phi: np.ndarray,
    want_esdf: bool,
    want_grad: bool,
    want_phi: bool,
    out_esdf: np.ndarray,
    out_grad: np.ndarray,
    out_phi: np.ndarray,
) -> None:
    """The lookup of :class:`FieldStack` for compiled callers: point ``n`` of scene ``ids[n]`` into ``out_*[n]``.

    The flat field arrays are :class:`FieldStack`'s; only the ``want_*`` outputs are written (the others may be
    empty arrays). Kernels that must agree with the stack's lookups to the bit call this function with the flags as
    runtime arguments: literal flags let LLVM specialise the inlined fastmath point lookup, which can round
    differently (docs/expert.md, the band kernel).
    """
    for n in range(ids.shape[0]):
        e, g0, g1, g2, p = trilinear_point(
            ids[n], pts[n, 0], pts[n, 1], pts[n, 2], offset, shape, origin, res, esdf, grad, phi,
            want_esdf, want_grad, want_phi,
        )  # fmt: skip
        if want_esdf:
            out_esdf[n] = e
        if want_grad:
            out_grad[n, 0] = g0
            out_grad[n, 1] = g1
            out_grad[n, 2] = g2
        if want_phi:
            out_phi[n] = p


class FieldStack:
    """Several scenes' fields packed for batched lookups (numpy in, float64 numpy out).

    Args:
        fields: A sequence of :class:`envs.fields.SceneFields`; ``scene_ids`` index into it.

    :meth:`lazy` makes a stack whose scenes are built (or read from the cache) on the first query that names
    them, so an env over many scenes starts with only the scenes it flies.

    Memory: 20 bytes per node (ESDF, 3 gradient components and Phi as float32); a 64 x 32 x 3 m scene at
    0.1 m (6.4 M nodes) takes about 128 MB. A lazy stack reserves the flat arrays with ``np.zeros``, whose pages
    the OS maps only when a scene is written into them.
    """

    def __init__(self, fields: Sequence) -> None:
        fields = list(fields)
        if not fields:
            raise ValueError("FieldStack needs at least one SceneFields")
        self._setup([f.shape for f in fields], [f.origin for f in fields], [f.res for f in fields], None)
        for s, f in enumerate(fields):
            self._put(s, f, share=False)

    @classmethod
    def lazy(cls, grids: Sequence, build: Callable[[int], Any]) -> FieldStack:
        """A stack over ``grids`` (one :class:`envs.fields.Grid` per scene) whose scene ``s`` is ``build(s)``.

        ``build`` is called on the first query (or :meth:`ensure`) that names ``s`` and must return a
        :class:`envs.fields.SceneFields` on that grid.
        """
        grids = list(grids)
        if not grids:
            raise ValueError("FieldStack needs at least one scene")
        self = cls.__new__(cls)
        self._setup([g.shape for g in grids], [g.origin for g in grids], [g.res for g in grids], build)
        return self

    def _setup(self, shapes: list, origins: list, res: list, build: Callable[[int], Any] | None) -> None:
        self.num_scenes = len(shapes)
        self.shape = np.array(shapes, dtype=np.int64).reshape(-1, 3)
        self.origin = np.array(origins, dtype=np.float64).reshape(-1, 3)
        self.res = np.array(res, dtype=np.float64)
        sizes = self.shape.prod(axis=1)
        self.offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        total = int(sizes.sum())
        self.phi_unreachable = np.zeros(self.num_scenes)
        self._esdf = np.zeros(total, dtype=np.float32)
        self._phi = np.zeros(total, dtype=np.float32)
        self._grad = np.zeros((total, 3), dtype=np.float32)
        self._fields: list = [None] * self.num_scenes
        self._ready = np.zeros(self.num_scenes, dtype=bool)
        self._all_ready = False
        self._build = build
        self._empty1 = np.zeros(0)
        self._empty3 = np.zeros((0, 3))

    def _put(self, s: int, f: Any, share: bool) -> None:
        """Copy scene ``s``'s fields into the flat arrays (``share``: point ``f``'s arrays at the copies)."""
        if tuple(f.shape) != tuple(self.shape[s]):
            raise ValueError(f"scene {s}: fields of shape {tuple(f.shape)} where the stack expects "
                             f"{tuple(self.shape[s].tolist())}")  # fmt: skip
        lo, n = int(self.offset[s]), int(np.prod(f.shape))
        self._esdf[lo : lo + n] = f.esdf.reshape(-1)
        self._phi[lo : lo + n] = f.phi.reshape(-1)
        self._grad[lo : lo + n] = f.grad.reshape(-1, 3)
        if share:  # one copy in memory: the SceneFields reads the stack's arrays
            f.esdf = self._esdf[lo : lo + n].reshape(f.shape)
            f.phi = self._phi[lo : lo + n].reshape(f.shape)
            f.grad = self._grad[lo : lo + n].reshape(*f.shape, 3)
        self.phi_unreachable[s] = f.phi_unreachable
        self._fields[s] = f
        self._ready[s] = True
        self._all_ready = bool(self._ready.all())

    @property
    def ready(self) -> np.ndarray:
        """Which scenes are built (bool (S,), a copy)."""
        return self._ready.copy()

    def ensure(self, scene_ids: np.ndarray | Sequence[int]) -> None:
        """Build (or read from the cache) every scene of ``scene_ids`` that is not built yet."""
        if self._all_ready:
            return
        ids = np.asarray(scene_ids, dtype=np.int64).reshape(-1)
        for s in np.unique(ids[~self._ready[ids]]).tolist():
            self._put(s, self._build(s), share=True)

    def scene_fields(self, s: int) -> Any:
        """Scene ``s``'s :class:`envs.fields.SceneFields` (built first if the stack is lazy and it is not yet)."""
        if not 0 <= s < self.num_scenes:
            raise ValueError(f"scene id must lie in 0..{self.num_scenes - 1}; got {s}")
        self.ensure([s])
        return self._fields[s]

    def _check(self, scene_ids: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids = np.asarray(scene_ids)
        pts = np.asarray(points, dtype=np.float64)
        if ids.ndim != 1 or pts.shape != (ids.shape[0], 3):
            raise ValueError(f"expected scene_ids (N,) and points (N, 3); got {ids.shape} and {pts.shape}")
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_scenes):
            raise ValueError(f"scene_ids must lie in 0..{self.num_scenes - 1}; got {ids.min()}..{ids.max()}")
        if not np.isfinite(pts).all():
            bad = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
            raise ValueError(f"points must be finite; row {bad} is {pts[bad].tolist()}")
        ids = ids.astype(np.int64, copy=False)
        if not self._all_ready:
            self.ensure(ids)
        return ids, np.ascontiguousarray(pts)

    def query(
        self, scene_ids: np.ndarray, points: np.ndarray, esdf: bool = True, grad: bool = True, geodesic: bool = True
    ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """All requested fields in one pass: ``(esdf (N,), esdf_grad (N, 3), geodesic (N,))``, None if not asked."""
        ids, pts = self._check(scene_ids, points)
        n = ids.shape[0]
        out_e = np.empty(n) if esdf else self._empty1
        out_g = np.empty((n, 3)) if grad else self._empty3
        out_p = np.empty(n) if geodesic else self._empty1
        trilinear_batch(
            ids, pts, self.offset, self.shape, self.origin, self.res, self._esdf, self._grad, self._phi,
            esdf, grad, geodesic, out_e, out_g, out_p,
        )  # fmt: skip
        return (out_e if esdf else None, out_g if grad else None, out_p if geodesic else None)

    def kernel_fields(self, scene_ids: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(index (N,), offset, shape, origin, res, esdf, grad, phi)`` for :func:`trilinear_point` in a kernel.

        Builds the fields of ``scene_ids`` first (a lazy stack); ``index`` is the field of each entry (its scene).
        """
        ids = np.asarray(scene_ids, dtype=np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_scenes):
            raise ValueError(f"scene_ids must lie in 0..{self.num_scenes - 1}; got {ids.min()}..{ids.max()}")
        self.ensure(ids)
        return ids, self.offset, self.shape, self.origin, self.res, self._esdf, self._grad, self._phi

    def esdf(self, scene_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Signed distance to the nearest obstacle (N,), metres, negative inside."""
        return self.query(scene_ids, points, True, False, False)[0]  # type: ignore[return-value]

    def esdf_grad(self, scene_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Interpolated ESDF gradient (N, 3) (unit length away from medial axes)."""
        return self.query(scene_ids, points, False, True, False)[1]  # type: ignore[return-value]

    def geodesic(self, scene_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Geodesic distance to the goal region (N,), metres (finite; see ``phi_unreachable``)."""
        return self.query(scene_ids, points, False, False, True)[2]  # type: ignore[return-value]
