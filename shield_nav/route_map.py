"""A route from an onboard map: the goal input a depth policy steers by, re-aimed along a planned route.

Beyond the paper. In the benchmark's Perlin box fields the way to the goal often turns away from it (docs/results.md,
"What holds 3-5 m/s down"), which the depth image does not show and the policy's goal input (the goal's direction)
does not say. This layer gives the policy that direction from what the vehicle itself has seen, with no privileged
information: its depth images, its position (odometry) and the goal.

1. **Map.** A 2D occupancy grid per vehicle over its scene's footprint (``cell`` spacing): every depth pixel with a
   return whose world point lies between ``z_min`` and ``z_max`` marks its cell occupied (the same world points the
   shield uses, :func:`envs.camera.pointcloud.depth_to_points`). Unseen cells count as free (an optimistic map: the
   route heads for the goal until the vehicle has seen what is in the way). Cells are never cleared (static scenes).
2. **Route.** Every ``replan_steps`` control steps: the geodesic distance to the goal region over the cells farther
   than ``inflate`` from every occupied one (:func:`envs.fields.geodesic.geodesic_field` on a one-layer grid, the
   goal region always traversable), then steepest descent from the vehicle's cell over its 8 neighbours for
   ``lookahead`` metres; the carrot is where that ends (the goal itself while nothing is mapped, or when the
   vehicle's cell cannot reach it on the map).
3. **Input.** The state's ``goal_xy_h`` becomes the carrot's direction in the heading frame, scaled as the env scales
   the goal offset (``min(|goal offset|, 10 m) / 10``), so the policy still sees how far the goal is. With the carrot
   at the goal it is the env's own input (to float rounding).

Evaluation rows opt in with ``route_map: true`` (``configs/eval/rows.yaml``); parameters are the eval config's
``route_map`` section. The policy is unchanged: it was trained on the goal's direction in geometric clutter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from envs.camera.pointcloud import depth_to_points
from envs.config import require
from envs.fields.geodesic import geodesic_field
from envs.navigation.env import STATE_LAYOUT

_GOAL_COL = sum(k for name, k, _ in STATE_LAYOUT[: [n for n, _, _ in STATE_LAYOUT].index("goal_xy_h")])
"""First column of ``goal_xy_h`` in the policy's state vector."""
_GOAL_SCALE = 10.0
"""The env's goal-offset scale [m] (``NavigationEnv._state``: offset / max(|offset|, 10 m))."""
_NEIGHBOURS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)], dtype=np.int64)


@dataclass
class RouteMapConfig:
    """Parameters of :class:`OnboardRoute` (an eval config's ``route_map`` section)."""

    cell: float = 0.25
    """Spacing of the occupancy grid [m]."""
    z_min: float = 0.3
    """Lowest world height of a depth point that marks its cell occupied [m] (keeps the floor out)."""
    z_max: float = 2.7
    """Highest such height [m]."""
    inflate: float = 0.5
    """Clearance the route keeps from every occupied cell [m]."""
    lookahead: float = 8.0
    """Arc length of the route from the vehicle to the carrot [m]."""
    replan_steps: int = 10
    """Control steps between route plans (the map takes every image)."""

    def validate(self, prefix: str = "") -> None:
        """Raise ``ConfigError`` naming the first bad field."""
        for name in ("cell", "inflate", "lookahead"):
            require(getattr(self, name) > 0, f"{prefix}{name}", "must be > 0")
        require(self.z_max > self.z_min, f"{prefix}z_max", f"must be > z_min ({self.z_min})")
        require(self.replan_steps >= 1, f"{prefix}replan_steps", "must be >= 1")


class OnboardRoute:
    """Per-vehicle occupancy maps, routes and carrots for a ``NavigationEnv`` batch (see the module docstring)."""

    def __init__(self, cfg: RouteMapConfig, camera: Any) -> None:  # noqa: D107
        cfg.validate("route_map.")
        self.cfg = cfg
        self.camera = camera
        self.occ: list[np.ndarray] = []
        self.lo = np.zeros((0, 2))
        self.carrot = np.zeros((0, 2))
        self.steps = 0
        self.plans = 0

    def reset(self, env: Any) -> None:
        """Empty maps over each vehicle's scene footprint; carrots at the goals. Call after ``env.reset``."""
        c = self.cfg.cell
        self.occ, lo = [], []
        for sid in env.scene_id_buf:
            scene = env.scenes[int(sid)]
            lo_i, hi_i = np.asarray(scene.bounds_lo[:2], float), np.asarray(scene.bounds_hi[:2], float)
            shape = np.maximum(np.ceil((hi_i - lo_i) / c).astype(int) + 1, 2)
            self.occ.append(np.zeros(tuple(shape), dtype=bool))
            lo.append(lo_i)
        self.lo = np.array(lo)
        self.carrot = np.array(env.goal_buf[:, :2], dtype=float)
        self.steps = 0
        self.observe(env)

    def observe(self, env: Any) -> None:
        """Mark the cells of every vehicle's newest depth image (``env.sensor_depth_buf``)."""
        cfg = self.cfg
        for i, occ in enumerate(self.occ):
            pts = depth_to_points(env.sensor_depth_buf[i], env.local_pos[i], env.vehicles.R_wb[i], self.camera)
            pts = pts[(pts[:, 2] >= cfg.z_min) & (pts[:, 2] <= cfg.z_max)]
            ij = np.round((pts[:, :2] - self.lo[i]) / cfg.cell).astype(np.int64)
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < occ.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < occ.shape[1])
            occ[ij[inside, 0], ij[inside, 1]] = True

    def plan(self, env: Any, i: int) -> np.ndarray:
        """The carrot (2,) of vehicle ``i`` on its current map (the goal where the map gives no route)."""
        cfg, occ = self.cfg, self.occ[i]
        goal = np.asarray(env.goal_buf[i, :2], float)
        if not occ.any():
            return goal
        c = cfg.cell
        trav = ndimage.distance_transform_edt(~occ, sampling=c) > cfg.inflate
        gx = self.lo[i, 0] + c * np.arange(occ.shape[0])
        gy = self.lo[i, 1] + c * np.arange(occ.shape[1])
        goal_mask = (gx[:, None] - goal[0]) ** 2 + (gy[None, :] - goal[1]) ** 2 <= env.cfg.episode.goal_radius**2
        if not goal_mask.any():  # a goal region smaller than a cell: its nearest cell
            goal_mask[self._cell(i, goal)] = True
        trav |= goal_mask
        diag = float(np.hypot(*(np.array(occ.shape) * c)))
        phi, unreachable, _ = geodesic_field(trav[..., None], goal_mask[..., None], c, diag)
        phi = phi[..., 0]
        a, b = self._cell(i, env.local_pos[i, :2])
        if phi[a, b] >= unreachable:
            return goal
        length = 0.0
        while length < cfg.lookahead and not goal_mask[a, b]:
            nb = _NEIGHBOURS + (a, b)
            ok = (nb[:, 0] >= 0) & (nb[:, 0] < occ.shape[0]) & (nb[:, 1] >= 0) & (nb[:, 1] < occ.shape[1])
            vals = np.where(ok, phi[np.clip(nb[:, 0], 0, occ.shape[0] - 1), np.clip(nb[:, 1], 0, occ.shape[1] - 1)],
                            np.inf)  # fmt: skip
            k = int(np.argmin(vals))
            if not vals[k] < phi[a, b]:
                break
            a, b = int(nb[k, 0]), int(nb[k, 1])
            length += c * float(np.hypot(*_NEIGHBOURS[k]))
        return self.lo[i] + c * np.array([a, b], dtype=float)

    def _cell(self, i: int, xy: np.ndarray) -> tuple[int, int]:
        ij = np.round((np.asarray(xy, float) - self.lo[i]) / self.cfg.cell).astype(np.int64)
        ij = np.clip(ij, 0, np.array(self.occ[i].shape) - 1)
        return int(ij[0]), int(ij[1])

    def steer(self, env: Any, state: np.ndarray) -> np.ndarray:
        """A copy of the policy's state (N, 21) with ``goal_xy_h`` aimed at each carrot; re-plans on schedule."""
        if self.steps % self.cfg.replan_steps == 0:
            self.carrot = np.array([self.plan(env, i) for i in range(len(self.occ))])
            self.plans += 1
        self.steps += 1
        pos = env.local_pos[:, :2]
        to_goal = np.linalg.norm(env.goal_buf[:, :2] - pos, axis=1)
        d = self.carrot - pos
        r = env.vehicles.R_wb
        psi = np.arctan2(r[:, 1, 0], r[:, 0, 0])
        cs, sn = np.cos(psi), np.sin(psi)
        d_h = np.stack((cs * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + cs * d[:, 1]), axis=1)
        norm = np.linalg.norm(d_h, axis=1, keepdims=True)
        scale = np.minimum(to_goal, _GOAL_SCALE)[:, None] / _GOAL_SCALE
        out = np.array(state, copy=True)
        out[:, _GOAL_COL : _GOAL_COL + 2] = np.where(norm > 1e-9, d_h / np.maximum(norm, 1e-9) * scale, 0.0)
        return out
