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
=========================  ============================================================================
"""

from __future__ import annotations

import numpy as np

from envs.fields import SceneFields, region_mask
from envs.scenes.families import OBSTACLE_X_MARGIN
from envs.scenes.scene import Scene

COLUMNS = (
    "family", "index", "obstacles", "moving", "occupied_%", "median_esdf_m", "free_path_m", "tortuosity",
    "start_reach_%",
)  # fmt: skip


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
    }


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
