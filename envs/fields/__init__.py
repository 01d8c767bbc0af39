"""Privileged scene fields: occupancy, signed ESDF (+ gradient), Dijkstra geodesic field Phi_g, lookups.

Batched trilinear lookups serve many scenes at once (one numba pass over all query points).

Public API::

    from envs.fields import build_fields, FieldStack
    f = build_fields(scene, resolution=0.1, vehicle_radius=0.2)   # cached on disk
    stack = FieldStack([f0, f1, ...])                              # or scene_field_stack(scenes): lazy
    d, g, phi = stack.query(scene_ids, points)                     # (N,), (N, 3), (N,)

See :mod:`envs.fields.esdf`, :mod:`envs.fields.geodesic` and :mod:`envs.fields.lookup` for the math.
"""

from envs.fields.build import (
    DEFAULT_RESOLUTION,
    DEFAULT_STENCIL,
    DEFAULT_VEHICLE_RADIUS,
    SceneFields,
    build_fields,
    cache_key,
    default_cache_dir,
    region_mask,
    scene_field_stack,
)
from envs.fields.esdf import Grid
from envs.fields.geodesic import geodesic_field, stencil
from envs.fields.lookup import FieldStack

__all__ = [
    "DEFAULT_RESOLUTION",
    "DEFAULT_STENCIL",
    "DEFAULT_VEHICLE_RADIUS",
    "FieldStack",
    "Grid",
    "SceneFields",
    "build_fields",
    "cache_key",
    "default_cache_dir",
    "geodesic_field",
    "region_mask",
    "scene_field_stack",
    "stencil",
]
