"""Shared MJCF conventions: collision bits and geom groups used by vehicles and scenes.

Contacts happen between two geoms when ``(contype_a & conaffinity_b) or (contype_b & conaffinity_a)``.
With the bits below, vehicles collide with obstacles (and floor/ceiling) but never with each other, and
obstacles never test against each other. Geom groups let ray casts (``mj_multiRay``'s ``geomgroup``) see
only obstacles, never the vehicles.
"""

OBSTACLE_CONTYPE = 1
OBSTACLE_CONAFFINITY = 2
VEHICLE_CONTYPE = 2
VEHICLE_CONAFFINITY = 1

OBSTACLE_GROUP = 1
"""Geom group of scene obstacles, floor and ceiling (what depth cameras see)."""
VEHICLE_GROUP = 2
"""Geom group of vehicle geoms (invisible to depth cameras)."""


def fmt(values: object) -> str:
    """Format a float or a sequence of floats for an MJCF attribute, with full float64 precision."""
    if isinstance(values, (int, float)):
        return repr(float(values))
    return " ".join(repr(float(v)) for v in values)  # type: ignore[union-attr]
