"""Geometric primitives that scenes are made of: the single contract shared by physics, fields and cameras.

Every obstacle in every scene family is one of four exact shapes (composites such as frames and trees are
expanded into these when a scene is generated):

============  =========================================  ==============================================
kind          parameters (world frame, metres)           MuJoCo geom
============  =========================================  ==============================================
``sphere``    ``center`` (3), ``radius``                 ``type="sphere"``
``cylinder``  axis endpoints ``p0``, ``p1`` (3), radius   ``type="cylinder" fromto=...`` (flat caps)
``capsule``   axis endpoints ``p0``, ``p1`` (3), radius   ``type="capsule" fromto=...`` (round caps)
``box``       ``center`` (3), ``half`` extents (3),       ``type="box"``, rotated by ``quat``
              ``quat`` (w, x, y, z, body-to-world)
============  =========================================  ==============================================

Vertical and inclined cylinders differ only in their endpoints; thin poles are capsules or cylinders with a
small radius. Each primitive serialises to a plain dict (``to_dict``/``primitive_from_dict``) so a scene is
JSON-able, and to an MJCF ``<geom>`` element (``to_mjcf``) carrying the obstacle collision bits and group.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.mjcf import OBSTACLE_CONAFFINITY, OBSTACLE_CONTYPE, OBSTACLE_GROUP, fmt

_GEOM_COMMON = (
    f'contype="{OBSTACLE_CONTYPE}" conaffinity="{OBSTACLE_CONAFFINITY}" group="{OBSTACLE_GROUP}" rgba="0.55 0.5 0.45 1"'
)


def _vec3(name: str, value: Any) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return value


@dataclass(frozen=True)
class Sphere:
    """A sphere. ``center`` in metres (world), ``radius`` in metres."""

    center: tuple[float, float, float]
    radius: float
    kind = "sphere"

    def __post_init__(self) -> None:  # noqa: D105
        object.__setattr__(self, "center", _vec3("sphere.center", self.center))
        object.__setattr__(self, "radius", _positive("sphere.radius", self.radius))

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo, hi)``, each shape (3,)."""
        c = np.array(self.center)
        return c - self.radius, c + self.radius

    def to_mjcf(self) -> str:
        """The MJCF ``<geom>`` element."""
        return f'<geom type="sphere" pos="{fmt(self.center)}" size="{fmt(self.radius)}" {_GEOM_COMMON}/>'

    def to_dict(self) -> dict:
        """A JSON-able dict with a ``kind`` tag."""
        return {"kind": self.kind, "center": list(self.center), "radius": self.radius}


@dataclass(frozen=True)
class _Segment:
    """Shared parts of the two segment-based shapes (cylinder, capsule)."""

    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float
    kind = "segment"

    def __post_init__(self) -> None:  # noqa: D105
        object.__setattr__(self, "p0", _vec3(f"{self.kind}.p0", self.p0))
        object.__setattr__(self, "p1", _vec3(f"{self.kind}.p1", self.p1))
        object.__setattr__(self, "radius", _positive(f"{self.kind}.radius", self.radius))
        if np.linalg.norm(np.subtract(self.p1, self.p0)) < 1e-9:
            raise ValueError(f"{self.kind} endpoints p0 and p1 coincide: {self.p0}")

    @property
    def length(self) -> float:
        """Axis length in metres."""
        return float(np.linalg.norm(np.subtract(self.p1, self.p0)))

    def to_mjcf(self) -> str:
        """The MJCF ``<geom>`` element (``fromto`` form)."""
        return f'<geom type="{self.kind}" fromto="{fmt(self.p0 + self.p1)}" size="{fmt(self.radius)}" {_GEOM_COMMON}/>'

    def to_dict(self) -> dict:
        """A JSON-able dict with a ``kind`` tag."""
        return {"kind": self.kind, "p0": list(self.p0), "p1": list(self.p1), "radius": self.radius}


@dataclass(frozen=True)
class Cylinder(_Segment):
    """A solid cylinder with flat caps between axis endpoints ``p0`` and ``p1`` (vertical or inclined)."""

    kind = "cylinder"

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact axis-aligned bounding box ``(lo, hi)`` of the capped cylinder."""
        p0, p1 = np.array(self.p0), np.array(self.p1)
        u = (p1 - p0) / np.linalg.norm(p1 - p0)
        # Extent of the cap disc along world axis k: r * sqrt(1 - u_k^2).
        ext = self.radius * np.sqrt(np.clip(1.0 - u * u, 0.0, 1.0))
        return np.minimum(p0, p1) - ext, np.maximum(p0, p1) + ext


@dataclass(frozen=True)
class Capsule(_Segment):
    """A capsule (swept sphere) between axis endpoints ``p0`` and ``p1``: thin poles and tree canopies."""

    kind = "capsule"

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo, hi)``."""
        p0, p1 = np.array(self.p0), np.array(self.p1)
        return np.minimum(p0, p1) - self.radius, np.maximum(p0, p1) + self.radius


@dataclass(frozen=True)
class Box:
    """An oriented box: ``center``, ``half`` extents (metres) and ``quat`` (w, x, y, z) rotating box to world."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    kind = "box"

    def __post_init__(self) -> None:  # noqa: D105
        object.__setattr__(self, "center", _vec3("box.center", self.center))
        half = _vec3("box.half", self.half)
        for h in half:
            _positive("box.half", h)
        object.__setattr__(self, "half", half)
        q = np.asarray(self.quat, dtype=float).reshape(-1)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
            raise ValueError(f"box.quat must be a finite non-zero quaternion (w, x, y, z), got {self.quat}")
        q = q / np.linalg.norm(q)
        object.__setattr__(self, "quat", tuple(float(v) for v in q))

    def rotation(self) -> np.ndarray:
        """Rotation matrix (3, 3) from box frame to world frame."""
        w, x, y, z = self.quat
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact axis-aligned bounding box ``(lo, hi)`` of the rotated box."""
        ext = np.abs(self.rotation()) @ np.array(self.half)
        c = np.array(self.center)
        return c - ext, c + ext

    def to_mjcf(self) -> str:
        """The MJCF ``<geom>`` element."""
        return (
            f'<geom type="box" pos="{fmt(self.center)}" size="{fmt(self.half)}" quat="{fmt(self.quat)}" '
            f"{_GEOM_COMMON}/>"
        )

    def to_dict(self) -> dict:
        """A JSON-able dict with a ``kind`` tag."""
        return {"kind": self.kind, "center": list(self.center), "half": list(self.half), "quat": list(self.quat)}


Primitive = Sphere | Cylinder | Capsule | Box
PRIMITIVE_TYPES: dict[str, type] = {"sphere": Sphere, "cylinder": Cylinder, "capsule": Capsule, "box": Box}


def primitive_from_dict(data: dict) -> Primitive:
    """Rebuild a primitive from :meth:`to_dict` output. Raises ``ValueError`` naming a bad kind or field."""
    data = dict(data)
    kind = data.pop("kind", None)
    if kind not in PRIMITIVE_TYPES:
        raise ValueError(f"unknown primitive kind {kind!r}; expected one of {sorted(PRIMITIVE_TYPES)}")
    try:
        return PRIMITIVE_TYPES[kind](**data)
    except TypeError as err:
        raise ValueError(f"bad fields for primitive kind {kind!r}: {err}") from None
