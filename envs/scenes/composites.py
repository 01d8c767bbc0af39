"""Composite obstacles (expanded into primitives at generation time) and footprint-based placement.

Every composite is returned as a list of primitives that lie inside ``[z_lo, z_hi]`` and a horizontal
*footprint* circle ``(x, y, R)`` enclosing it. :class:`Placer` scatters footprints with a minimum clearance
``gap`` between any two of them. Because every pair of footprints is at least ``gap`` apart and each obstacle
lies inside its footprint, a vehicle of radius below ``gap / 2`` can always slip between any two obstacles,
so scenes built this way stay traversable by construction (U-traps are open cups whose inside is part of
their footprint: nothing else is placed in them, they are dead ends, never blockers).
"""

from __future__ import annotations

import math

import numpy as np

from envs.scenes.primitives import Box, Capsule, Cylinder, Primitive, Sphere

Footprint = tuple[float, float, float]


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation by ``yaw`` radians about +z."""
    return (math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw))


def vertical_cylinder(x: float, y: float, r: float, z_lo: float, z_hi: float) -> tuple[list[Primitive], Footprint]:
    """A vertical cylinder from the floor ``z_lo`` to ``z_hi``."""
    return [Cylinder((x, y, z_lo), (x, y, z_hi), r)], (x, y, r)


def inclined_segment(
    kind: type, x: float, y: float, r: float, tilt: float, heading: float, z_lo: float, z_hi: float
) -> tuple[list[Primitive], Footprint]:
    """An inclined cylinder or capsule leaning by ``tilt`` (rad from vertical) towards ``heading`` (rad).

    Its axis passes through ``(x, y)`` at mid height. The end points are pulled in along the axis so the flat
    cap discs (cylinder: they stick out by ``r sin(tilt)`` in z) or end spheres (capsule: by ``r``) stay
    inside ``[z_lo, z_hi]``.
    """
    u = np.array([math.sin(tilt) * math.cos(heading), math.sin(tilt) * math.sin(heading), math.cos(tilt)])
    margin = r * math.sin(tilt) if kind is Cylinder else r  # vertical overhang of an end
    half_h = 0.5 * (z_hi - z_lo) - margin - 1e-6  # vertical half-extent of the axis
    half_len = half_h / u[2]
    mid = np.array([x, y, 0.5 * (z_lo + z_hi)])
    p0, p1 = mid - half_len * u, mid + half_len * u
    reach = half_len * math.sin(tilt) + r  # horizontal extent from (x, y)
    return [kind(tuple(p0), tuple(p1), r)], (x, y, reach)


def box_column(
    x: float, y: float, hx: float, hy: float, yaw: float, z_lo: float, z_hi: float
) -> tuple[list[Primitive], Footprint]:
    """A box standing on the floor, rotated by ``yaw``: pillars (square) and wall pieces (elongated)."""
    hz = 0.5 * (z_hi - z_lo)
    return [Box((x, y, z_lo + hz), (hx, hy, hz), yaw_quat(yaw))], (x, y, math.hypot(hx, hy))


def sphere_blob(x: float, y: float, z: float, r: float) -> tuple[list[Primitive], Footprint]:
    """A floating sphere (its z must leave it inside the bounds)."""
    return [Sphere((x, y, z), r)], (x, y, r)


def frame(
    x: float,
    y: float,
    width: float,
    yaw: float,
    z_lo: float,
    z_hi: float,
    bar_heights: tuple[float, ...],
    post_r: float = 0.08,
    bar_r: float = 0.06,
) -> tuple[list[Primitive], Footprint]:
    """A door- or window-like frame: two vertical posts ``width`` apart plus horizontal crossbar(s).

    One bar high up is a door (fly under it); a low and a high bar make a window (fly between them).
    ``yaw`` is the direction of the line joining the posts.
    """
    d = np.array([math.cos(yaw), math.sin(yaw)]) * 0.5 * width
    a, b = np.array([x, y]) - d, np.array([x, y]) + d
    prims: list[Primitive] = [
        Cylinder((a[0], a[1], z_lo), (a[0], a[1], z_hi), post_r),
        Cylinder((b[0], b[1], z_lo), (b[0], b[1], z_hi), post_r),
    ]
    for h in bar_heights:
        prims.append(Cylinder((a[0], a[1], h), (b[0], b[1], h), bar_r))
    return prims, (x, y, 0.5 * width + post_r)


def tree(
    x: float, y: float, trunk_r: float, canopy_r: float, canopy_lo: float, z_lo: float, z_hi: float
) -> tuple[list[Primitive], Footprint]:
    """A tree: a trunk cylinder from the floor plus a vertical capsule canopy from ``canopy_lo`` to the top."""
    prims: list[Primitive] = [Cylinder((x, y, z_lo), (x, y, z_hi), trunk_r)]
    c0, c1 = canopy_lo + canopy_r, z_hi - canopy_r - 1e-6
    if c1 - c0 > 1e-3:
        prims.append(Capsule((x, y, c0), (x, y, c1), canopy_r))
    elif z_hi - canopy_lo >= 2.0 * canopy_r:
        prims.append(Sphere((x, y, 0.5 * (canopy_lo + z_hi)), canopy_r))
    return prims, (x, y, max(trunk_r, canopy_r))


def u_trap(
    x: float, y: float, width: float, depth: float, yaw: float, z_lo: float, z_hi: float, thickness: float = 0.2
) -> tuple[list[Primitive], Footprint]:
    """A U-shaped trap (a dead-end cup) of inner ``width`` x ``depth`` whose opening faces ``yaw + pi``.

    With ``yaw = 0`` the closed end is at +x (downstream) and the opening faces the start line, so a greedy
    flyer heading for the goal enters it and must back out. Three full-height walls: back and two sides.
    """
    c, s = math.cos(yaw), math.sin(yaw)

    def to_world(u: float, v: float) -> tuple[float, float]:
        return x + c * u - s * v, y + s * u + c * v

    t = 0.5 * thickness
    hz = 0.5 * (z_hi - z_lo)
    zc = z_lo + hz
    q = yaw_quat(yaw)
    back = to_world(0.5 * depth + t, 0.0)
    left = to_world(0.0, 0.5 * width + t)
    right = to_world(0.0, -(0.5 * width + t))
    prims: list[Primitive] = [
        Box((back[0], back[1], zc), (t, 0.5 * width + thickness, hz), q),
        Box((left[0], left[1], zc), (0.5 * depth, t, hz), q),
        Box((right[0], right[1], zc), (0.5 * depth, t, hz), q),
    ]
    radius = math.hypot(0.5 * depth + thickness, 0.5 * width + thickness)
    return prims, (x, y, radius)


class Placer:
    """Random sequential placement of footprint circles with a minimum clearance between them.

    Args:
        rng: Random generator (the only source of randomness).
        x_range: (min, max) x of the band every footprint circle must lie inside (m).
        y_range: (min, max) y of that band (m).
        gap: Minimum clearance (m) between any two footprints.
    """

    def __init__(
        self, rng: np.random.Generator, x_range: tuple[float, float], y_range: tuple[float, float], gap: float
    ) -> None:
        self.rng = rng
        self.x_range = x_range
        self.y_range = y_range
        self.gap = gap
        self._fp = np.zeros((0, 3))

    def free(self, fp: Footprint) -> bool:
        """Whether footprint ``fp`` fits inside the band and keeps ``gap`` from every placed footprint."""
        x, y, r = fp
        if x - r < self.x_range[0] or x + r > self.x_range[1] or y - r < self.y_range[0] or y + r > self.y_range[1]:
            return False
        if len(self._fp) == 0:
            return True
        d = np.hypot(self._fp[:, 0] - x, self._fp[:, 1] - y)
        return bool(np.all(d >= self._fp[:, 2] + r + self.gap))

    def add(self, fp: Footprint) -> None:
        """Record a placed footprint."""
        self._fp = np.vstack([self._fp, np.asarray(fp, dtype=float)[None, :]])

    def sample_xy(self, margin: float) -> tuple[float, float]:
        """A uniform candidate centre at least ``margin`` inside the band."""
        x = self.rng.uniform(self.x_range[0] + margin, self.x_range[1] - margin)
        y = self.rng.uniform(self.y_range[0] + margin, self.y_range[1] - margin)
        return float(x), float(y)

    def place(self, make: object, radius_hint: float, tries: int = 40) -> list[Primitive]:
        """Try up to ``tries`` random centres for ``make(x, y) -> (prims, footprint)``; [] if none fits."""
        for _ in range(tries):
            x, y = self.sample_xy(radius_hint)
            prims, fp = make(x, y)  # type: ignore[operator]
            if self.free(fp):
                self.add(fp)
                return prims
        return []

    @property
    def count(self) -> int:
        """Number of footprints placed so far."""
        return len(self._fp)
