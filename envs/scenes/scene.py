"""The scene model: a frozen, JSON-able description of one clutter world.

A :class:`Scene` is pure data (bounds, start/goal regions, static primitives, optional floor and ceiling,
moving obstacles) plus conversions:

* :meth:`Scene.to_mjcf_geoms` / :meth:`Scene.moving_mjcf_bodies`: MJCF fragments for the physics (and the
  depth camera, which ray-casts the very same geoms),
* :meth:`Scene.to_trimesh`: a ``trimesh.Scene`` for ``.obj``/``.glb`` export and figures,
* :meth:`Scene.to_dict` / :meth:`Scene.from_dict` (and :meth:`save` / :meth:`load` for JSON files).

Frame: x forward (start at ``bounds_lo.x``, goal at ``bounds_hi.x``), y left, z up, metres. All positions are
in the scene's own frame; a caller that tiles several scenes in one MuJoCo world passes an ``offset``.

Floor and ceiling are **finite boxes** (slabs 0.1 m thick) covering exactly the xy extent of the bounds, with
their inner faces at ``bounds_lo.z`` (floor top) and ``bounds_hi.z`` (ceiling bottom). Finite boxes rather than
planes so that tiled scenes do not see each other's floors, and so that what the camera sees is exactly what
the fields module treats as an obstacle (the fields add them as the analytic half-spaces ``z - z_lo`` and
``z_hi - z`` inside the bounds).

Moving obstacles (:class:`MovingObstacle`) are vertical cylinders translating horizontally at constant
velocity and bouncing elastically off the xy bounds (their axis stays ``radius`` away from each side). They are
*not* part of the static fields; :meth:`Scene.moving_positions` gives their positions at any time.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.mjcf import OBSTACLE_CONAFFINITY, OBSTACLE_CONTYPE, OBSTACLE_GROUP, fmt
from envs.scenes.primitives import Box, Capsule, Cylinder, Primitive, Sphere, primitive_from_dict

SCENE_FORMAT_VERSION = 1
"""Version tag written by :meth:`Scene.to_dict`; bump when the dict layout changes."""

SLAB_THICKNESS = 0.1
"""Thickness (m) of the floor and ceiling boxes in MJCF and trimesh output."""

BOUNDS_TOL = 1e-6
"""Tolerance (m) when checking that obstacles and regions lie inside the bounds."""

Vec3 = tuple[float, float, float]
Region = tuple[Vec3, Vec3]

DEFAULT_BOUNDS_LO: Vec3 = (0.0, -16.0, 0.0)
DEFAULT_BOUNDS_HI: Vec3 = (64.0, 16.0, 3.0)


def _vec3(name: str, value: Any) -> Vec3:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"scene {name} must be 3 finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _region(name: str, value: Any) -> Region:
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise ValueError(f"scene {name} must be a (lo, hi) pair of 3-vectors, got {value!r}") from None
    lo, hi = _vec3(f"{name}.lo", lo), _vec3(f"{name}.hi", hi)
    if not all(a < b for a, b in zip(lo, hi, strict=True)):
        raise ValueError(f"scene {name} must have lo < hi on every axis, got lo={lo} hi={hi}")
    return lo, hi


def _region_z(lo: Vec3, hi: Vec3) -> tuple[float, float]:
    """A 2 m tall z band centred in the bounds (the whole height if the bounds are lower than 2 m)."""
    zc, half = 0.5 * (lo[2] + hi[2]), min(1.0, 0.5 * (hi[2] - lo[2]))
    return zc - half, zc + half


def default_start_region(lo: Vec3 = DEFAULT_BOUNDS_LO, hi: Vec3 = DEFAULT_BOUNDS_HI) -> Region:
    """The paper's 1 x W x 2 m start box at the start line (x in [lo, lo+1]), centred in height."""
    z0, z1 = _region_z(lo, hi)
    return (lo[0], lo[1], z0), (min(lo[0] + 1.0, hi[0]), hi[1], z1)


def default_goal_region(lo: Vec3 = DEFAULT_BOUNDS_LO, hi: Vec3 = DEFAULT_BOUNDS_HI) -> Region:
    """The paper's 1 x W x 2 m goal box at the far end (x in [hi-1, hi]), centred in height."""
    z0, z1 = _region_z(lo, hi)
    return (max(hi[0] - 1.0, lo[0]), lo[1], z0), (hi[0], hi[1], z1)


@dataclass(frozen=True)
class MovingObstacle:
    """A vertical cylinder moving horizontally at constant velocity, bouncing off the xy scene bounds.

    Attributes:
        cylinder: The obstacle at t = 0. Must be vertical (p0, p1 share x and y).
        velocity: Horizontal velocity ``(vx, vy)`` in m/s.
    """

    cylinder: Cylinder
    velocity: tuple[float, float]

    def __post_init__(self) -> None:  # noqa: D105
        if not isinstance(self.cylinder, Cylinder):
            raise ValueError(f"moving obstacle must be a Cylinder, got {type(self.cylinder).__name__}")
        p0, p1 = self.cylinder.p0, self.cylinder.p1
        if abs(p0[0] - p1[0]) > 1e-9 or abs(p0[1] - p1[1]) > 1e-9:
            raise ValueError(f"moving obstacle cylinder must be vertical, got p0={p0} p1={p1}")
        if p0[2] > p1[2]:  # normalise so that p0 is the base
            object.__setattr__(self, "cylinder", Cylinder(p1, p0, self.cylinder.radius))
        v = np.asarray(self.velocity, dtype=float).reshape(-1)
        if v.shape != (2,) or not np.all(np.isfinite(v)):
            raise ValueError(f"moving obstacle velocity must be 2 finite numbers (vx, vy), got {self.velocity!r}")
        object.__setattr__(self, "velocity", (float(v[0]), float(v[1])))

    def to_dict(self) -> dict:
        """A JSON-able dict."""
        return {"cylinder": self.cylinder.to_dict(), "velocity": list(self.velocity)}

    @staticmethod
    def from_dict(data: dict) -> MovingObstacle:
        """Inverse of :meth:`to_dict`."""
        prim = primitive_from_dict(data["cylinder"])
        return MovingObstacle(prim, tuple(data["velocity"]))  # type: ignore[arg-type]


def _bounce(s: np.ndarray, length: float | np.ndarray) -> np.ndarray:
    """Fold an unbounded coordinate ``s`` (relative to the lower wall) into ``[0, L]`` by elastic reflection.

    Triangle wave: with ``m = s mod 2L``, the folded coordinate is ``L - |m - L|``
    (``m`` in [0, L] maps to m; ``m`` in [L, 2L] maps to 2L - m, the mirrored leg).
    """
    period = 2.0 * length
    m = np.mod(s, period)
    return length - np.abs(m - length)


@dataclass(frozen=True)
class Scene:
    """One clutter world. Frozen, hashable by content (:meth:`digest`), JSON-able.

    Attributes:
        bounds_lo: Lower corner of the flight volume (m).
        bounds_hi: Upper corner of the flight volume (m).
        start_region: ``(lo, hi)`` box where episodes start (None: the 1 m deep, full-width, 2 m tall box at
            the ``bounds_lo.x`` end, centred in height).
        goal_region: ``(lo, hi)`` box the geodesic field flows to (None: the same box at the ``bounds_hi.x`` end).
        primitives: Static obstacles; every primitive's bounding box lies inside the bounds.
        floor: Whether a floor slab sits under ``bounds_lo.z`` (a collision surface).
        ceiling: Whether a ceiling slab sits above ``bounds_hi.z`` (a collision surface).
        moving: Moving obstacles (dynamic family); not part of the static fields.
        family: Name of the generating family ("custom" for hand-made scenes).
        index: Index within the family.
        seed: Base seed the scene was generated from.
    """

    bounds_lo: Vec3 = DEFAULT_BOUNDS_LO
    bounds_hi: Vec3 = DEFAULT_BOUNDS_HI
    start_region: Region | None = None
    goal_region: Region | None = None
    primitives: tuple[Primitive, ...] = ()
    floor: bool = True
    ceiling: bool = False
    moving: tuple[MovingObstacle, ...] = ()
    family: str = "custom"
    index: int = 0
    seed: int = 0

    def __post_init__(self) -> None:  # noqa: D105
        lo, hi = _region("bounds", (self.bounds_lo, self.bounds_hi))
        object.__setattr__(self, "bounds_lo", lo)
        object.__setattr__(self, "bounds_hi", hi)
        if self.start_region is None:
            object.__setattr__(self, "start_region", default_start_region(lo, hi))
        if self.goal_region is None:
            object.__setattr__(self, "goal_region", default_goal_region(lo, hi))
        for name in ("start_region", "goal_region"):
            r_lo, r_hi = _region(name, getattr(self, name))
            if any(r_lo[k] < lo[k] - BOUNDS_TOL or r_hi[k] > hi[k] + BOUNDS_TOL for k in range(3)):
                raise ValueError(f"scene {name} {r_lo}..{r_hi} is not inside the bounds {lo}..{hi}")
            object.__setattr__(self, name, (r_lo, r_hi))
        prims = tuple(self.primitives)
        for i, prim in enumerate(prims):
            if not isinstance(prim, (Sphere, Cylinder, Capsule, Box)):
                raise ValueError(f"primitive {i} is not a scene primitive: {type(prim).__name__}")
            a_lo, a_hi = prim.aabb()
            if np.any(a_lo < np.array(lo) - BOUNDS_TOL) or np.any(a_hi > np.array(hi) + BOUNDS_TOL):
                raise ValueError(
                    f"primitive {i} ({prim.kind}) lies outside the scene bounds {lo}..{hi}: "
                    f"its bounding box is {np.round(a_lo, 4).tolist()}..{np.round(a_hi, 4).tolist()}"
                )
        object.__setattr__(self, "primitives", prims)
        moving = tuple(self.moving)
        for i, mob in enumerate(moving):
            if not isinstance(mob, MovingObstacle):
                raise ValueError(f"moving obstacle {i} is not a MovingObstacle: {type(mob).__name__}")
            c = mob.cylinder
            r = c.radius
            x, y = c.p0[0], c.p0[1]
            if not (lo[0] + r <= x + BOUNDS_TOL and x <= hi[0] - r + BOUNDS_TOL) or not (
                lo[1] + r <= y + BOUNDS_TOL and y <= hi[1] - r + BOUNDS_TOL
            ):
                raise ValueError(f"moving obstacle {i} at ({x}, {y}) with radius {r} lies outside the xy bounds")
            if c.p0[2] < lo[2] - BOUNDS_TOL or c.p1[2] > hi[2] + BOUNDS_TOL:
                raise ValueError(f"moving obstacle {i} spans z {c.p0[2]}..{c.p1[2]}, outside the bounds")
        object.__setattr__(self, "moving", moving)
        object.__setattr__(self, "floor", bool(self.floor))
        object.__setattr__(self, "ceiling", bool(self.ceiling))
        object.__setattr__(self, "index", int(self.index))
        object.__setattr__(self, "seed", int(self.seed))

    # ------------------------------------------------------------------ geometry helpers
    @property
    def size(self) -> np.ndarray:
        """Extent ``hi - lo`` (3,) in metres."""
        return np.subtract(self.bounds_hi, self.bounds_lo)

    @property
    def goal_center(self) -> np.ndarray:
        """Centre (3,) of the goal region."""
        return 0.5 * (np.asarray(self.goal_region[0]) + np.asarray(self.goal_region[1]))

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """A plain JSON-able dict (round-trips through :meth:`from_dict`)."""
        return {
            "version": SCENE_FORMAT_VERSION,
            "family": self.family,
            "index": self.index,
            "seed": self.seed,
            "bounds_lo": list(self.bounds_lo),
            "bounds_hi": list(self.bounds_hi),
            "start_region": [list(self.start_region[0]), list(self.start_region[1])],
            "goal_region": [list(self.goal_region[0]), list(self.goal_region[1])],
            "floor": self.floor,
            "ceiling": self.ceiling,
            "primitives": [p.to_dict() for p in self.primitives],
            "moving": [m.to_dict() for m in self.moving],
        }

    @staticmethod
    def from_dict(data: dict) -> Scene:
        """Rebuild and validate a scene from :meth:`to_dict` output.

        Raises:
            ValueError: Naming the bad key, primitive index or value (negative radius, obstacle outside
                the bounds, unknown key, unsupported version, ...).
        """
        data = dict(data)
        version = data.pop("version", SCENE_FORMAT_VERSION)
        if version != SCENE_FORMAT_VERSION:
            raise ValueError(f"unsupported scene format version {version!r} (expected {SCENE_FORMAT_VERSION})")
        known = {
            "family", "index", "seed", "bounds_lo", "bounds_hi", "start_region", "goal_region",
            "floor", "ceiling", "primitives", "moving",
        }  # fmt: skip
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown scene key(s) {unknown}; expected a subset of {sorted(known)}")
        prims = []
        for i, p in enumerate(data.pop("primitives", [])):
            try:
                prims.append(primitive_from_dict(p))
            except ValueError as err:
                raise ValueError(f"primitive {i}: {err}") from None
        moving = []
        for i, m in enumerate(data.pop("moving", [])):
            try:
                moving.append(MovingObstacle.from_dict(m))
            except (ValueError, KeyError, TypeError) as err:
                raise ValueError(f"moving obstacle {i}: {err}") from None
        for key in ("bounds_lo", "bounds_hi"):
            if key in data:
                data[key] = tuple(data[key])
        for key in ("start_region", "goal_region"):
            if key in data:
                data[key] = tuple(tuple(v) for v in data[key])
        return Scene(primitives=tuple(prims), moving=tuple(moving), **data)

    def to_json(self) -> str:
        """Canonical JSON text (sorted keys, compact); :meth:`digest` hashes exactly this."""
        return json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))

    def digest(self) -> str:
        """SHA-256 hex digest of :meth:`to_json`: the scene's content identity (used by the field cache)."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()

    def save(self, path: str | os.PathLike) -> None:
        """Write the scene as indented JSON."""
        with open(path, "w") as f:
            json.dump(self.to_dict(), f, indent=1)

    @staticmethod
    def load(path: str | os.PathLike) -> Scene:
        """Read a scene JSON file written by :meth:`save` (validated; errors name the file)."""
        with open(path) as f:
            data = json.load(f)
        try:
            return Scene.from_dict(data)
        except ValueError as err:
            raise ValueError(f"scene file {os.fspath(path)!r}: {err}") from None

    # ------------------------------------------------------------------ MuJoCo
    def _slabs(self) -> list[tuple[str, Box]]:
        """``(name, box)`` for the floor and ceiling (outside the bounds in z, exactly covering them in xy)."""
        lo, hi = np.array(self.bounds_lo), np.array(self.bounds_hi)
        cxy = 0.5 * (lo[:2] + hi[:2])
        hxy = 0.5 * (hi[:2] - lo[:2])
        t = 0.5 * SLAB_THICKNESS
        out = []
        if self.floor:
            out.append(("floor", Box((cxy[0], cxy[1], lo[2] - t), (hxy[0], hxy[1], t))))
        if self.ceiling:
            out.append(("ceiling", Box((cxy[0], cxy[1], hi[2] + t), (hxy[0], hxy[1], t))))
        return out

    def to_mjcf_geoms(self, offset: tuple[float, float, float] = (0.0, 0.0, 0.0), prefix: str = "") -> str:
        """MJCF ``<geom>`` elements (for ``<worldbody>``): static primitives, floor and ceiling, shifted by ``offset``.

        Args:
            offset: World-frame translation (m) applied to every geom (for tiling scenes).
            prefix: Prefix for the geom names (unique names when several scenes share one model).

        Returns:
            A newline-separated MJCF fragment. Geoms carry the obstacle collision bits and group.
        """
        off = np.asarray(offset, dtype=float)
        lines = []
        for i, prim in enumerate(self.primitives):
            lines.append(_named(_translated(prim, off).to_mjcf(), f"{prefix}obs{i}"))
        for name, slab in self._slabs():
            lines.append(_named(_translated(slab, off).to_mjcf(), f"{prefix}{name}"))
        return "\n".join(lines)

    def moving_mjcf_bodies(self, offset: tuple[float, float, float] = (0.0, 0.0, 0.0), prefix: str = "") -> str:
        """MJCF mocap ``<body>`` elements, one per moving obstacle, named ``{prefix}moving{i}``.

        The body frame sits at the obstacle's base centre (t = 0 position plus ``offset``); its cylinder geom
        extends upwards from there. Drive it by writing ``data.mocap_pos`` with :meth:`moving_positions`
        (plus the offset).
        """
        off = np.asarray(offset, dtype=float)
        lines = []
        for i, mob in enumerate(self.moving):
            c = mob.cylinder
            base = np.asarray(c.p0) + off
            half_h = 0.5 * c.length
            lines.append(
                f'<body name="{prefix}moving{i}" mocap="true" pos="{fmt(base)}">'
                f'<geom name="{prefix}moving{i}_geom" type="cylinder" pos="0 0 {fmt(half_h)}" '
                f'size="{fmt((c.radius, half_h))}" contype="{OBSTACLE_CONTYPE}" '
                f'conaffinity="{OBSTACLE_CONAFFINITY}" group="{OBSTACLE_GROUP}" rgba="0.8 0.3 0.2 1"/></body>'
            )
        return "\n".join(lines)

    def to_mjcf(self) -> str:
        """A complete, compilable MJCF model of the scene alone (static geoms and mocap bodies)."""
        return (
            '<mujoco model="scene">\n<worldbody>\n'
            + self.to_mjcf_geoms()
            + "\n"
            + self.moving_mjcf_bodies()
            + "\n</worldbody>\n</mujoco>\n"
        )

    # ------------------------------------------------------------------ moving obstacles
    def moving_positions(self, t: float | np.ndarray) -> np.ndarray:
        """Base-centre positions of the moving obstacles at time(s) ``t`` (s), with elastic bouncing.

        Each axis (x, y) bounces independently inside ``[lo + r, hi - r]``; z stays at the base height.

        Args:
            t: A scalar time or an array of times of shape (T,).

        Returns:
            Shape (M, 3) for a scalar ``t``, (T, M, 3) for an array; M = ``len(self.moving)``.
        """
        t_arr = np.asarray(t, dtype=float)
        scalar = t_arr.ndim == 0
        tt = t_arr.reshape(-1, 1)  # (T, 1)
        m = len(self.moving)
        out = np.zeros((tt.shape[0], m, 3))
        if m:
            base = np.array([mob.cylinder.p0 for mob in self.moving])  # (M, 3)
            vel = np.array([mob.velocity for mob in self.moving])  # (M, 2)
            rad = np.array([mob.cylinder.radius for mob in self.moving])  # (M,)
            for k in range(2):
                lo_k = self.bounds_lo[k] + rad  # (M,) lowest admissible axis coordinate
                length = (self.bounds_hi[k] - rad) - lo_k  # (M,) admissible span
                s = (base[:, k] - lo_k)[None, :] + vel[None, :, k] * tt  # unbounded travel (T, M)
                out[:, :, k] = lo_k[None, :] + _bounce(s, length[None, :])
            out[:, :, 2] = base[None, :, 2]
        return out[0] if scalar else out

    # ------------------------------------------------------------------ trimesh
    def to_trimesh(self, include_slabs: bool = False, t: float = 0.0) -> Any:
        """A ``trimesh.Scene`` with one mesh per primitive (and moving obstacles at time ``t``).

        Args:
            include_slabs: Also add the floor and ceiling boxes.
            t: Time (s) at which moving obstacles are placed.
        """
        import trimesh

        ts = trimesh.Scene()
        for i, prim in enumerate(self.primitives):
            ts.add_geometry(primitive_mesh(prim), node_name=f"obs{i}", geom_name=f"obs{i}")
        if self.moving:
            pos = self.moving_positions(t)
            for i, mob in enumerate(self.moving):
                c = mob.cylinder
                shift = pos[i] - np.asarray(c.p0)
                moved = Cylinder(tuple(np.asarray(c.p0) + shift), tuple(np.asarray(c.p1) + shift), c.radius)
                ts.add_geometry(primitive_mesh(moved), node_name=f"moving{i}", geom_name=f"moving{i}")
        if include_slabs:
            for name, slab in self._slabs():
                ts.add_geometry(primitive_mesh(slab), node_name=name, geom_name=name)
        return ts


def _named(geom_xml: str, name: str) -> str:
    """Insert ``name="..."`` into a ``<geom .../>`` element."""
    return geom_xml.replace("<geom ", f'<geom name="{name}" ', 1)


def _translated(prim: Primitive, off: np.ndarray) -> Primitive:
    """A copy of ``prim`` shifted by ``off`` (3,)."""
    if not np.any(off):
        return prim
    if isinstance(prim, Sphere):
        return Sphere(tuple(np.asarray(prim.center) + off), prim.radius)
    if isinstance(prim, Box):
        return Box(tuple(np.asarray(prim.center) + off), prim.half, prim.quat)
    return type(prim)(tuple(np.asarray(prim.p0) + off), tuple(np.asarray(prim.p1) + off), prim.radius)


def _segment_transform(p0: tuple, p1: tuple) -> np.ndarray:
    """Homogeneous transform placing a z-aligned, origin-centred mesh along the segment p0 -> p1."""
    import trimesh

    a0, a1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    tf = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], a1 - a0)
    tf[:3, 3] = 0.5 * (a0 + a1)
    return tf


def primitive_mesh(prim: Primitive) -> Any:
    """A watertight ``trimesh.Trimesh`` of one primitive (metres, scene frame)."""
    import trimesh

    if isinstance(prim, Sphere):
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=prim.radius)
        mesh.apply_translation(prim.center)
        return mesh
    if isinstance(prim, Box):
        tf = np.eye(4)
        tf[:3, :3] = prim.rotation()
        tf[:3, 3] = prim.center
        return trimesh.creation.box(extents=2.0 * np.asarray(prim.half), transform=tf)
    sections = 24 if prim.radius > 0.1 else 12
    if isinstance(prim, Capsule):
        # trimesh's capsule is centred at the origin with its sphere centres at z = +-height/2.
        mesh = trimesh.creation.capsule(height=prim.length, radius=prim.radius, count=[sections, sections])
    else:
        mesh = trimesh.creation.cylinder(radius=prim.radius, height=prim.length, sections=sections)
    mesh.apply_transform(_segment_transform(prim.p0, prim.p1))
    return mesh


def scene_volume(scene: Scene) -> float:
    """Volume (m^3) of the scene bounds."""
    return float(math.prod(scene.size))
