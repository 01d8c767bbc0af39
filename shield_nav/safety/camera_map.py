"""The camera map: what each flight's camera has shown, as a 2D occupancy grid, and an optimistic plan over it.

Used by the stall escape (:mod:`shield_nav.safety.escape`), the ``reactive_map`` baseline and the camera-routed expert.
Reads nothing privileged.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from envs.camera.config import CameraConfig
from envs.camera.model import R_bc, ray_dirs_c, ray_grid
from envs.camera.pointcloud import depth_to_points
from envs.fields.geodesic import geodesic_field

if TYPE_CHECKING:  # the escape's config types the map's settings; the escape imports this module
    from shield_nav.safety.escape import EscapeConfig


class CameraMap:
    """What each flight's camera has shown, as a 2D occupancy grid, and an optimistic plan over it.

    One grid of ``map_cell`` cells per flight over the flight volume's horizontal ``bounds``; :meth:`observe` marks
    the cells of the depth image's points within ``map_range`` of the vehicle and ``map_band`` of its height (and
    ``map_floor`` above the floor); :meth:`plan` runs a Dijkstra from the goal region (``goal_radius``) over the
    grid with mapped cells inflated by ``map_inflate`` and unmapped cells free, and descends it ``lookahead`` metres
    from the vehicle. Used by the stall escape's ``kind: map`` and by the ``reactive_map`` baseline
    (:class:`shield_nav.algorithms.baselines.MapReactivePlanner`). Reads nothing privileged.
    """

    def __init__(self, cfg: EscapeConfig, n: int, camera: CameraConfig, lo: np.ndarray, hi: np.ndarray) -> None:  # noqa: D107
        cfg.validate("escape.")
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(2) for b in (lo, hi))
        if not (hi > lo).all():
            raise ValueError(f"camera map: the bounds' upper corner {hi.tolist()} must exceed the lower {lo.tolist()}")
        shape = np.maximum(np.ceil((hi - lo) / cfg.map_cell).astype(int), 1)
        self.cfg, self.camera, self.lo = cfg, camera, lo
        self.grid = np.zeros((n, int(shape[0]), int(shape[1])), dtype=bool)
        """(n, nx, ny) bool: cells the camera has shown occupied."""
        self.seen = np.zeros_like(self.grid) if cfg.map_unknown_cost > 1.0 else None
        """(n, nx, ny) bool: cells an image has shown, free or not (kept only with ``map_unknown_cost`` > 1)."""
        self._rays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.next_plan = np.zeros(n, dtype=np.int64)
        """(n,) the control step from which each flight is due for a plan again (:meth:`due`)."""

    def observe(self, ids: np.ndarray, pos: np.ndarray, R_wb: np.ndarray, depth_m: np.ndarray, floor: float) -> None:  # noqa: N803
        """Mark the cells of flights ``ids``' image points near their height.

        ``pos`` (N, 3), ``R_wb`` (N, 3, 3): the vehicles' positions and attitudes in the frame of the bounds;
        ``depth_m`` (N, 1, H, W) metric depth (0 or non-finite: no return); ``floor``: the volume's floor height.
        """
        cfg, grid = self.cfg, self.grid
        nx, ny = grid.shape[1:]
        for i in ids:
            pts = depth_to_points(depth_m[i], pos[i], R_wb[i], self.camera)  # type: ignore[arg-type]
            near = np.linalg.norm(pts[:, :2] - pos[i, :2], axis=1) <= cfg.map_range
            band = (np.abs(pts[:, 2] - pos[i, 2]) <= cfg.map_band) & (pts[:, 2] >= floor + cfg.map_floor)
            p = pts[near & band]
            cx = np.floor((p[:, 0] - self.lo[0]) / cfg.map_cell).astype(np.int64)
            cy = np.floor((p[:, 1] - self.lo[1]) / cfg.map_cell).astype(np.int64)
            ok = (cx >= 0) & (cx < nx) & (cy >= 0) & (cy < ny)
            grid[i, cx[ok], cy[ok]] = True
            if self.seen is not None:
                self._mark_seen(int(i), pos[i], R_wb[i], depth_m[i], floor)

    def _mark_seen(self, i: int, pos: np.ndarray, R_wb: np.ndarray, depth_m: np.ndarray, floor: float) -> None:  # noqa: N803
        """Mark the cells flight ``i``'s image showed.

        Along each image column's bearing, from the camera to its nearest return within the height band
        (``map_band`` of the vehicle, ``map_floor`` above the floor), or where no pixel of the band returns, to the
        farthest point the band's pixels saw free (``max_range``); at most ``map_range`` metres.
        """
        cfg, cam = self.cfg, self.camera
        if self._rays is None:  # the camera's pixel rays and its columns' centre rays (camera frame), once
            x_u = ray_grid(cam)[0]
            self._rays = (ray_dirs_c(cam), np.stack((x_u, np.zeros_like(x_u), np.ones_like(x_u)), axis=1), R_bc(cam))
        rays, columns, r_bc = self._rays
        r_wc = R_wb @ r_bc
        o = pos + R_wb @ np.asarray(cam.mount_pos_b, dtype=np.float64)
        z = np.asarray(depth_m, dtype=np.float64).reshape(cam.height, cam.width)
        ret = (z > 0.0) & (z < cam.max_range)  # a surface; otherwise (no return, or NaN) free up to the range
        z = np.where(ret, z, cam.max_range)
        pts = o + z[..., None] * (rays @ r_wc.T)  # (H, W, 3): p_w = o_w + R_wc z (x_u, y_v, 1)
        band = (np.abs(pts[..., 2] - pos[2]) <= cfg.map_band) & (pts[..., 2] >= floor + cfg.map_floor)
        dist = np.hypot(pts[..., 0] - o[0], pts[..., 1] - o[1])
        hit = np.where(band & ret, dist, np.inf).min(axis=0)
        free = np.where(np.isfinite(hit), hit, np.where(band & ~ret, dist, 0.0).max(axis=0))
        free = np.minimum(free, cfg.map_range)
        bearing = (columns @ r_wc.T)[:, :2]
        norm = np.linalg.norm(bearing, axis=1)
        keep = (norm > 1e-9) & (free > 0.0)  # a column looking straight up or down has no bearing
        step = 0.5 * cfg.map_cell
        t = np.arange(0.0, cfg.map_range + step, step)
        t = np.where(t[None, :] <= free[keep, None], t[None, :], np.nan)  # (columns, samples)
        u = bearing[keep] / norm[keep, None]
        px, py = o[0] + t * u[:, :1], o[1] + t * u[:, 1:]
        ok = np.isfinite(px)
        cx = np.floor((px[ok] - self.lo[0]) / cfg.map_cell).astype(np.int64)
        cy = np.floor((py[ok] - self.lo[1]) / cfg.map_cell).astype(np.int64)
        nx, ny = self.grid.shape[1:]
        inside = (cx >= 0) & (cx < nx) & (cy >= 0) & (cy < ny)
        self.seen[i, cx[inside], cy[inside]] = True  # type: ignore[index]

    @classmethod
    def for_env(cls, cfg: EscapeConfig, env: Any) -> CameraMap:
        """A map for every flight of a navigation env: one flight volume for all, and the env must render depth."""
        sc = env.scenes[0]
        if any(not (np.array_equal(env.scenes[k].bounds_lo, sc.bounds_lo)
                    and np.array_equal(env.scenes[k].bounds_hi, sc.bounds_hi))
               for k in np.unique(env.scene_id_buf)):  # fmt: skip
            raise ValueError("camera map: every env must fly a volume of the same bounds")
        if not env.cfg.render_depth:
            raise ValueError("camera map: it maps the depth image, so the env must render it (render_depth: true; a "
                             "row whose controller class says reads_depth = False skips the rendering)")  # fmt: skip
        return cls(cfg, env.num_envs, env.cfg.camera, sc.bounds_lo[:2], sc.bounds_hi[:2])

    def due(self, env: Any, step: int) -> np.ndarray:
        """The live flights of a navigation env due for a plan at control step ``step``.

        At steps that are multiples of ``map_every`` it first maps the live flights' images; each flight returned is
        booked for its next plan ``replan_s`` later. Any subset of steps may call it (the schedule reads ``step``,
        not the number of calls).
        """
        cfg = self.cfg
        live = np.flatnonzero(~env.frozen_buf)
        if step % cfg.map_every == 0:
            self.observe(
                live, env.local_pos, env.vehicles.R_wb, env.sensor_depth_buf, float(env.scenes[0].bounds_lo[2])
            )
        due = live[step >= self.next_plan[live]]
        self.next_plan[due] = step + max(int(round(cfg.replan_s / env.cfg.vehicle.command_dt)), 1)
        return due

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """The cells' centre coordinates along x (nx,) and y (ny,)."""
        nx, ny = self.grid.shape[1:]
        res = self.cfg.map_cell
        return self.lo[0] + (np.arange(nx) + 0.5) * res, self.lo[1] + (np.arange(ny) + 0.5) * res

    def field(
        self, i: int, goal: np.ndarray, covered_goal: str = "nan", clear: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Flight ``i``'s field (nx, ny) over its map and the goal disc's mask (nx, ny).

        The field is the path length [m] to the disc of ``goal_radius`` round ``goal``, mapped cells inflated by
        ``map_inflate`` and unmapped ones free. Where the mapped cells cover the whole disc: None (``covered_goal``
        ``"nan"``), or the disc kept a source (``"keep"``). ``clear``: :meth:`clearance` of flight ``i`` where the
        caller has it.
        """
        return self._field_on(self.grid[i], None if self.seen is None else self.seen[i], goal, covered_goal, clear)

    def _field_on(
        self, grid: np.ndarray, seen: np.ndarray | None, goal: np.ndarray, covered_goal: str = "nan",
        clear: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:  # fmt: skip
        """:meth:`field` over the given map (nx, ny) and shown cells (or None)."""
        cfg = self.cfg
        free = (_clearance(grid, cfg.map_cell) if clear is None else clear) > cfg.map_inflate
        to_goal = self._goal_disc(goal)
        if not (free & to_goal).any():
            if covered_goal == "nan":
                return None
            free |= to_goal
        cost = None if seen is None else np.where(seen, 1.0, cfg.map_unknown_cost)[..., None]
        out = geodesic_field(free[..., None], to_goal[..., None], cfg.map_cell, self._diag(), cost=cost)
        return out[0][..., 0], to_goal

    def narrow_field(
        self, i: int, goal: np.ndarray, radius: float, clearance: float, weight: float, clear: np.ndarray | None = None
    ) -> np.ndarray:
        """Flight ``i``'s narrow field (nx, ny), the expert's narrow field on the camera's map.

        The weighted path length to the goal disc through the cells more than ``radius`` from every mapped cell, each
        metre weighed ``1 + weight * max(0, clearance - d) / clearance`` (``d`` the distance to the nearest mapped
        cell), so its paths keep to the middle of corridors that ``map_inflate`` closes. The goal disc stays a source
        where mapped cells cover it. ``clear``: :meth:`clearance` of flight ``i`` where the caller has it.
        """
        if not (radius >= 0 and clearance > 0 and weight >= 0):
            raise ValueError(f"camera map: narrow field needs radius >= 0, clearance > 0, weight >= 0; got {radius}, "
                             f"{clearance}, {weight}")  # fmt: skip
        d = self.clearance(i) if clear is None else clear
        free = d > radius
        to_goal = self._goal_disc(goal)
        if not (free & to_goal).any():
            free |= to_goal
        cost = 1.0 + weight * np.clip(clearance - d, 0.0, None) / clearance  # d = inf (nothing mapped): 1
        out = geodesic_field(free[..., None], to_goal[..., None], self.cfg.map_cell, self._diag(), cost=cost[..., None])
        return out[0][..., 0]

    def clearance(self, i: int) -> np.ndarray:
        """Distance (nx, ny) [m] from each cell centre of flight ``i``'s map to the nearest mapped one (inf: none)."""
        return _clearance(self.grid[i], self.cfg.map_cell)

    def cell(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The map cells (M,), (M,) of points ``pos`` (M, >=2) in the frame of the bounds, clipped to the grid."""
        nx, ny = self.grid.shape[1:]
        res = self.cfg.map_cell
        a = np.clip(np.floor((pos[:, 0] - self.lo[0]) / res), 0, nx - 1).astype(np.int64)
        b = np.clip(np.floor((pos[:, 1] - self.lo[1]) / res), 0, ny - 1).astype(np.int64)
        return a, b

    def _goal_disc(self, goal: np.ndarray) -> np.ndarray:
        cx, cy = self.centres()
        return np.hypot(cx[:, None] - goal[0], cy[None, :] - goal[1]) <= self.cfg.goal_radius

    def _diag(self) -> float:
        return float(np.hypot(*(np.array(self.grid.shape[1:]) * self.cfg.map_cell)))

    def plan(self, i: int, pos: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """The point (2,) ``lookahead`` metres along the plan over flight ``i``'s map, or NaN: fly the true goal.

        NaN where the plan reaches the goal region within the lookahead or the mapped obstacles cover that region.
        """
        return self.plan_on(self.grid[i], None if self.seen is None else self.seen[i], pos, goal)

    def plan_on(self, grid: np.ndarray, seen: np.ndarray | None, pos: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """:meth:`plan` over the given map (nx, ny) and shown cells (or None).

        It reads nothing the map changes, so copies of a flight's map may be planned on another thread while the map
        takes the next images.
        """
        cfg = self.cfg
        out = self._field_on(grid, seen, goal)
        if out is None:
            return np.full(2, np.nan)  # the mapped obstacles cover the goal region: fly the true goal
        phi, to_goal = out
        nx, ny = phi.shape
        res = cfg.map_cell
        centres_x, centres_y = self.centres()
        a, b = (int(c[0]) for c in self.cell(pos[None]))  # the cells observe marks
        for _ in range(int(round(cfg.lookahead / res))):
            if to_goal[a, b]:
                return np.full(2, np.nan)
            a0, a1, b0, b1 = max(a - 1, 0), min(a + 2, nx), max(b - 1, 0), min(b + 2, ny)
            steps = np.hypot(*np.meshgrid(np.arange(a0, a1) - a, np.arange(b0, b1) - b, indexing="ij"))
            slope = (phi[a, b] - phi[a0:a1, b0:b1]) / np.maximum(steps, 1e-9)  # drop per cell length: a straight
            k = int(np.argmax(slope))  # step beats a diagonal one of the same drop
            if slope.flat[k] <= 0.0:
                break  # a local minimum of the plan
            a, b = a0 + k // slope.shape[1], b0 + k % slope.shape[1]
        return np.array([centres_x[a], centres_y[b]])


def _clearance(occ: np.ndarray, cell: float) -> np.ndarray:
    """Distance (nx, ny) [m] from each cell centre to the nearest marked cell of ``occ`` (inf: none marked)."""
    if not occ.any():
        return np.full(occ.shape, np.inf)
    return ndimage.distance_transform_edt(~occ, sampling=cell)
