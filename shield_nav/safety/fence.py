"""A geofence for the shield: the sides of the flight volume as obstacle points (docs/shield.md, "Geofence").

The task ends a flight that leaves its volume (the scene's bounds widened by ``episode.out_of_bounds_margin``), and
a deployed vehicle knows its geofence as it knows its goal. With :attr:`ShieldConfig.fence` on, each shield call adds
to the cloud, for each side plane within the shield's point range, the plane's point nearest to the vehicle: its
row is that of a wall, so the barrier lets the vehicle close on the fence only as fast as it can still stop
``r_safe`` short of it, and leaves flight along the fence free.
"""

from __future__ import annotations

import numpy as np


def fence_points(p: np.ndarray, box: np.ndarray, max_range: float) -> np.ndarray:
    """The points of a fence's side planes nearest to ``p`` (3,), for the planes closer than ``max_range``.

    ``box`` (2, 2) is ``[[x_lo, y_lo], [x_hi, y_hi]]``; a plane's nearest point is the foot of the perpendicular
    from ``p`` (at its height and its place along the plane). Returns (k, 3), k <= 4.
    """
    out = []
    for axis in (0, 1):
        for side in (0, 1):
            wall = float(box[side, axis])
            if abs(wall - p[axis]) < max_range:
                q = np.array(p, dtype=np.float64)
                q[axis] = wall
                out.append(q)
    return np.array(out).reshape(-1, 3)


def fence_boxes(fence: np.ndarray | None, num: int, on: bool, inset: float) -> np.ndarray | None:
    """``fence`` checked against the shield's ``fence`` switch ``on`` and broadcast to (num, 2, 2); None when off.

    Each box moves ``inset`` metres inwards on every side.

    Raises:
        ValueError: a fence given with the switch off, none given with it on, or a box that is not finite
            ``[[x_lo, y_lo], [x_hi, y_hi]]`` with lo < hi.
    """
    if not on:
        if fence is not None:
            raise ValueError("a fence box was given, but shield.fence is off; set shield.fence=true to use it")
        return None
    if fence is None:
        raise ValueError("shield.fence is on: give each vehicle's fence box [[x_lo, y_lo], [x_hi, y_hi]]")
    box = np.asarray(fence, dtype=np.float64)
    if box.shape == (2, 2):
        box = np.broadcast_to(box, (num, 2, 2))
    if box.shape != (num, 2, 2) or not np.all(np.isfinite(box)) or np.any(box[:, 0] + inset >= box[:, 1] - inset):
        got = np.asarray(fence).tolist() if box.size <= 8 else f"shape {box.shape}"
        raise ValueError(f"fence must be finite [[x_lo, y_lo], [x_hi, y_hi]] boxes with lo < hi after the inset "
                         f"({inset} m), shaped (2, 2) or ({num}, 2, 2); got {got}")  # fmt: skip
    return box + np.array([[inset, inset], [-inset, -inset]]) if inset else np.array(box)


def env_fence(env) -> np.ndarray:  # noqa: ANN001
    """Each vehicle's flight volume in a ``NavigationEnv`` as fence boxes (num_envs, 2, 2).

    The horizontal out-of-bounds boundary of its scene: the scene's bounds widened by ``episode.out_of_bounds_margin``.
    """
    m = env.cfg.episode.out_of_bounds_margin
    lo = np.array([s.bounds_lo[:2] for s in env.scenes])[env.scene_id_buf] - m
    hi = np.array([s.bounds_hi[:2] for s in env.scenes])[env.scene_id_buf] + m
    return np.stack((lo, hi), axis=1)
