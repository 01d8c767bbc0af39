"""Exact analytic signed distance functions of the scene primitives (metres, negative inside).

These are the ground truth the voxel ESDF in :mod:`envs.fields` is built from (near surfaces) and tested
against. All functions take points of shape (N, 3) and return shape (N,) float64.

Formulas (exact, for the solid shapes MuJoCo collides with):

* sphere:   ``|p - c| - r``
* capsule:  ``dist(p, segment p0p1) - r``
* cylinder (flat caps): in the cylinder frame with axial coordinate ``a`` (from the midpoint) and radial
  distance ``rho``, let ``q = (rho - r, |a| - h)`` with ``h`` the half length. Then
  ``sdf = min(max(q_0, q_1), 0) + |max(q, 0)|`` (inside: the larger of the two negative slab distances;
  outside: the Euclidean norm of the positive parts, i.e. distance to the nearest rim, disc or side).
* box: ``q = |R^T (p - c)| - half``, then ``sdf = |max(q, 0)| + min(max_k q_k, 0)`` (same construction).

For a union of shapes, ``min_i sdf_i`` is the exact distance outside the union; inside overlapping shapes it
is the depth into the deepest single shape, which may underestimate the depth into the union.
"""

from __future__ import annotations

import numpy as np

from envs.scenes.primitives import Box, Capsule, Cylinder, Primitive, Sphere


def _segment_frame(p0: tuple, p1: tuple, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Axial coordinate from the midpoint and radial distance of ``points`` w.r.t. the axis p0 -> p1."""
    a0, a1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    mid = 0.5 * (a0 + a1)
    axis = a1 - a0
    half_len = 0.5 * float(np.linalg.norm(axis))
    u = axis / (2.0 * half_len)
    rel = points - mid
    along = rel @ u  # (N,) signed axial coordinate
    radial = np.linalg.norm(rel - along[:, None] * u[None, :], axis=1)  # (N,) distance to the axis line
    return along, radial, half_len


def sdf_sphere(prim: Sphere, points: np.ndarray) -> np.ndarray:
    """Signed distance to a sphere: ``|p - c| - r``."""
    return np.linalg.norm(points - np.asarray(prim.center), axis=1) - prim.radius


def sdf_capsule(prim: Capsule, points: np.ndarray) -> np.ndarray:
    """Signed distance to a capsule: distance to the axis segment minus the radius."""
    along, radial, h = _segment_frame(prim.p0, prim.p1, points)
    # Distance to the segment: radial part plus the axial overshoot beyond the end points.
    over = np.maximum(np.abs(along) - h, 0.0)
    return np.hypot(radial, over) - prim.radius


def sdf_cylinder(prim: Cylinder, points: np.ndarray) -> np.ndarray:
    """Signed distance to a flat-capped cylinder (exact; see the module docstring)."""
    along, radial, h = _segment_frame(prim.p0, prim.p1, points)
    q0 = radial - prim.radius
    q1 = np.abs(along) - h
    inside = np.minimum(np.maximum(q0, q1), 0.0)
    outside = np.hypot(np.maximum(q0, 0.0), np.maximum(q1, 0.0))
    return inside + outside


def sdf_box(prim: Box, points: np.ndarray) -> np.ndarray:
    """Signed distance to an oriented box (exact; see the module docstring)."""
    local = (points - np.asarray(prim.center)) @ prim.rotation()  # rows: R^T (p - c)
    q = np.abs(local) - np.asarray(prim.half)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


_SDF = {"sphere": sdf_sphere, "capsule": sdf_capsule, "cylinder": sdf_cylinder, "box": sdf_box}


def primitive_sdf(prim: Primitive, points: np.ndarray) -> np.ndarray:
    """Signed distance (N,) from ``points`` (N, 3) to one primitive, metres, negative inside."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    return _SDF[prim.kind](prim, pts)


def union_sdf(prims: tuple[Primitive, ...] | list[Primitive], points: np.ndarray) -> np.ndarray:
    """``min_i sdf_i`` over primitives (N,); ``+inf`` where there are none. Fine for tests and small N."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.full(len(pts), np.inf)
    for prim in prims:
        np.minimum(out, primitive_sdf(prim, pts), out=out)
    return out
