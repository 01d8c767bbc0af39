"""Static scene statistics (difficulty measures), computed from the scene and its fields.

=========================  ============================================================================
column                     definition
=========================  ============================================================================
``obstacles``              number of static primitives (composites count once per primitive)
``moving``                 number of moving obstacles
``occupied_%``             percentage of grid nodes inside a static primitive (floor/ceiling excluded)
``median_esdf_m``          median obstacle-only ESDF over free nodes of the whole volume: the paper's
                           "median free-space ESDF" (floor and ceiling excluded, else a 3 m tall scene
                           could never exceed 0.75 m)
``free_path_m``            *mean straight free path along +x*: over traversable nodes (ESDF > vehicle
                           radius) in the obstacle zone at flight heights (the start region's z range),
                           the mean distance one can fly straight forward before leaving traversable
                           space. A substitute for AvoidBench's traversability, whose exact definition we
                           could not pin down (lower = harder)
``tortuosity``             median over reachable start-region nodes of Phi / (straight x distance to the
                           goal region): 1 for an empty scene, larger with detours and traps
``start_reach_%``          percentage of traversable start-region nodes that can reach the goal
``bottleneck_m``           *widest route*: the largest clearance ``r`` for which the nodes at flight
                           heights (the start region's z range) with ESDF > ``r`` still link the start
                           region to the goal region (26-connected; to the grid's resolution). The
                           vehicle's centre must pass within this distance of an obstacle on every route;
                           minus the vehicle radius it is the margin a controller has at the narrowest gap
                           (the ESDF includes floor and ceiling, so it is capped by the slab's height)
=========================  ============================================================================
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from envs.fields import SceneFields, region_mask
from envs.scenes.families import OBSTACLE_X_MARGIN
from envs.scenes.scene import Scene

COLUMNS = (
    "family", "index", "obstacles", "moving", "occupied_%", "median_esdf_m", "free_path_m", "tortuosity",
    "start_reach_%", "bottleneck_m",
)  # fmt: skip


def bottleneck_clearance(esdf: np.ndarray, start: np.ndarray, goal: np.ndarray, res: float) -> float:
    """Largest ``r`` such that nodes with ``esdf > r`` link a ``start`` node to a ``goal`` node (26-connected).

    Bisection on ``r`` to a tenth of the grid resolution; 0.0 when even ``r = 0`` does not link them.
    """
    structure = np.ones((3, 3, 3), dtype=bool)

    def linked(r: float) -> bool:
        labels, _ = ndimage.label(esdf > r, structure=structure)
        a, b = labels[start], labels[goal]
        return bool(np.intersect1d(a[a > 0], b[b > 0]).size)

    lo, hi = 0.0, float(esdf.max())
    if not linked(lo):
        return 0.0
    while hi - lo > 0.1 * res:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if linked(mid) else (lo, mid)
    return lo


def free_path_x(traversable: np.ndarray, res: float) -> np.ndarray:
    """Length (m) of the straight traversable run starting at each node and heading +x (0 where blocked).

    Recurrence from the far end: ``run[i] = (run[i+1] + res) * trav[i]`` (the last slice is ``0`` free path
    beyond the grid).
    """
    run = np.zeros(traversable.shape, dtype=np.float32)
    for i in range(traversable.shape[0] - 2, -1, -1):
        run[i] = (run[i + 1] + res) * traversable[i]
    return run


def scene_stats(scene: Scene, fields: SceneFields) -> dict:
    """One row of statistics (see the module docstring)."""
    grid = fields.grid
    trav = fields.traversable
    z_lo, z_hi = scene.start_region[0][2], scene.start_region[1][2]
    zone = region_mask(
        grid,
        (
            (scene.bounds_lo[0] + OBSTACLE_X_MARGIN, scene.bounds_lo[1], z_lo),
            (scene.bounds_hi[0] - OBSTACLE_X_MARGIN, scene.bounds_hi[1], z_hi),
        ),
    )
    run = free_path_x(trav, grid.res)
    sel = trav & zone
    start = region_mask(grid, scene.start_region) & trav
    x = grid.axis(0)[:, None, None] * np.ones(grid.shape)
    straight = np.maximum(scene.goal_region[0][0] - x, grid.res)
    reach = start & (fields.phi < fields.phi_unreachable)
    tort = float(np.median(fields.phi[reach] / straight[reach])) if reach.any() else float("nan")
    return {
        "family": scene.family,
        "index": scene.index,
        "obstacles": len(scene.primitives),
        "moving": len(scene.moving),
        "occupied_%": 100.0 * fields.info["occupied_fraction"],
        "median_esdf_m": fields.info["median_free_esdf"],
        "free_path_m": float(run[sel].mean()) if sel.any() else 0.0,
        "tortuosity": tort,
        "start_reach_%": 100.0 * float(reach.sum() / max(start.sum(), 1)),
        "bottleneck_m": _bottleneck(scene, fields, z_lo, z_hi),
    }


def _bottleneck(scene: Scene, fields: SceneFields, z_lo: float, z_hi: float) -> float:
    """``bottleneck_m`` of the module docstring: the slab of flight heights, start region to goal region."""
    grid = fields.grid
    z = grid.axis(2)
    k = np.flatnonzero((z >= z_lo - 1e-9) & (z <= z_hi + 1e-9))
    slab = slice(k[0], k[-1] + 1)
    start = region_mask(grid, scene.start_region)[:, :, slab]
    goal = region_mask(grid, scene.goal_region)[:, :, slab]
    return bottleneck_clearance(fields.esdf[:, :, slab], start, goal, grid.res)


def format_table(rows: list[dict]) -> str:
    """A Markdown table of stats rows."""
    head = "| " + " | ".join(COLUMNS) + " |"
    sep = "|" + "|".join("---:" if c not in ("family",) else "---" for c in COLUMNS) + "|"
    lines = [head, sep]
    for r in rows:
        cells = []
        for c in COLUMNS:
            v = r[c]
            cells.append(f"{v:.2f}" if isinstance(v, float) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
