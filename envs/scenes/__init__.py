"""Procedural clutter scenes: primitives, the :class:`Scene` model, the scene families and their statistics.

Public API::

    from envs.scenes import Scene, MovingObstacle, make_scene, FAMILIES
    scene = make_scene("benchmark", 3)        # deterministic from (family, index, seed)
    xml = scene.to_mjcf_geoms(offset=(0, 0, 0))

See ``docs/scenes.md`` for the families, the seed split and the statistics table.
"""

from envs.scenes.families import (
    EVAL_SEEDS,
    FAMILIES,
    TRAIN_SEEDS,
    Family,
    family_scenes,
    family_seed_range,
    is_training_family,
    make_scene,
)
from envs.scenes.primitives import Box, Capsule, Cylinder, Primitive, Sphere, primitive_from_dict
from envs.scenes.scene import MovingObstacle, Scene

__all__ = [
    "EVAL_SEEDS",
    "FAMILIES",
    "TRAIN_SEEDS",
    "Box",
    "Capsule",
    "Cylinder",
    "Family",
    "MovingObstacle",
    "Primitive",
    "Scene",
    "Sphere",
    "family_scenes",
    "family_seed_range",
    "is_training_family",
    "make_scene",
    "primitive_from_dict",
]
