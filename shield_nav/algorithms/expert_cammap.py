"""The camera-routed expert (row ``expert_cammap``).

The planning expert with its route taken from the map of what its own camera has shown, its tracker, local geometry
and narrow-corridor mode unchanged (docs/expert.md, "What an onboard map gives"). Privileged: it still reads the ESDF.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from envs.fields.lookup import trilinear_batch
from shield_nav.algorithms.expert import PlannerController
from shield_nav.safety.camera_map import CameraMap


class CameraMapPlanner(PlannerController):
    """The planning expert routed by what its own camera has shown (the ``expert_cammap`` row; a diagnostic).

    Path tracer, elastic band, speed profile and sampling tracker are the expert's, and so is their ESDF (the
    scene's: privileged local geometry); only Phi, the field the path descends and the route cost reads, is each
    flight's own: a Dijkstra over the 2D map of its depth images (:class:`shield_nav.safety.camera_map.CameraMap`,
    unmapped space free, mapped cells inflated by ``camera_map.map_inflate``, to a disc of ``camera_map.goal_radius``
    round the goal), replanned every ``camera_map.replan_s`` and extended over the volume's height by the height
    difference to the goal (as the scene's field grows away from the goal's height). Where the vehicle stands within
    ``map_inflate`` of what it mapped, or that field is flat, the path descends the expert's narrow field built on the
    same map instead (:meth:`shield_nav.safety.camera_map.CameraMap.narrow_field`: the vehicle radius,
    ``narrow_clearance``, ``narrow_weight``), and the tracker flies those flights as the expert flies its narrow-field
    ones. Against the ``expert`` row
    on the same trials it measures what the route a flyer without the map could know costs (docs/expert.md, "What an
    onboard map gives").
    """

    reads_depth = True

    def reset(self, env: Any) -> None:
        """Start a batch: empty maps and fields, every flight due for a plan."""
        super().reset(env)
        mc, sc, n = self.ec.camera_map, env.scenes[0], env.num_envs
        self._map = CameraMap.for_env(mc, env)
        res = mc.map_cell
        nx, ny = self._map.grid.shape[1:]
        self._nz = int(math.ceil((sc.bounds_hi[2] - sc.bounds_lo[2]) / res)) + 1
        size = nx * ny * self._nz
        self._shape = np.tile(np.array([[nx, ny, self._nz]], dtype=np.int64), (n, 1))
        origin = [sc.bounds_lo[0] + 0.5 * res, sc.bounds_lo[1] + 0.5 * res, sc.bounds_lo[2]]  # the cells' centres
        self._origin = np.tile(np.array([origin], dtype=np.float64), (n, 1))
        self._res = np.full(n, res, dtype=np.float64)
        self._offset = np.arange(n, dtype=np.int64) * size
        self._phi_flat = np.zeros(n * size, dtype=np.float32)
        self._narrow = self.ec.narrow_clearance > 0
        self._phi_narrow = np.zeros(n * size if self._narrow else 0, dtype=np.float32)
        self._radius = float(env.field_stack.scene_fields(int(env.scene_id_buf[0])).vehicle_radius)
        self._clear = np.full((n, nx, ny), np.inf, dtype=np.float32)  # each flight's distance to what it mapped
        self._step = 0
        self._env = env

    def restart(self, env: Any, ids: np.ndarray) -> None:
        """Flights ``ids`` start anew (a training env's own reset): empty maps, their images mapped now, a plan due.

        :meth:`commands` of this step then plans them on what their first image shows. Evaluation batches, which
        start every flight together, need not call it (:meth:`reset` does the same for all).
        """
        ids = np.asarray(ids, dtype=np.int64)
        m = self._map
        m.grid[ids] = False
        if m.seen is not None:
            m.seen[ids] = False
        m.next_plan[ids] = 0  # due now: commands() replans them (and their clearance) in this call
        m.observe(ids, env.local_pos, env.vehicles.R_wb, env.sensor_depth_buf, float(env.scenes[0].bounds_lo[2]))

    def phi_map(self, i: int, goal: np.ndarray) -> np.ndarray:
        """Flight ``i``'s field (nx, ny) [m] over its current map: the path length to the goal disc round ``goal``."""
        return self._map.field(i, goal, covered_goal="keep")[0]  # type: ignore[index]

    def commands(self, env: Any, among: np.ndarray | None = None) -> np.ndarray:
        """Map this step's images, replan the flights that are due, then the expert's command on those fields."""
        if getattr(self, "_env", None) is not env:
            self.reset(env)
        size = int(self._shape[0].prod())
        z = self._origin[0, 2] + np.arange(self._nz) * self.ec.camera_map.map_cell  # the layers' heights
        ec = self.ec
        for i in self._map.due(env, self._step):
            up = np.abs(z - env.goal_buf[i, 2])  # the climb or descent to the goal's height (the scene's field has it)
            o = int(self._offset[i])
            clear = self._map.clearance(int(i))  # one distance transform for both fields and the mode test
            phi = self._map.field(int(i), env.goal_buf[i], covered_goal="keep", clear=clear)[0]  # type: ignore[index]
            self._phi_flat[o : o + size] = (phi[:, :, None] + up[None, None, :]).astype(np.float32).ravel()
            if self._narrow:
                self._clear[i] = clear
                phi = self._map.narrow_field(int(i), env.goal_buf[i], self._radius, ec.narrow_clearance,
                                             ec.narrow_weight, clear=clear)  # fmt: skip
                self._phi_narrow[o : o + size] = (phi[:, :, None] + up[None, None, :]).astype(np.float32).ravel()
        self._step += 1
        return super().commands(env)

    def _closed(self, env: Any, slope: np.ndarray) -> np.ndarray:
        """The flights that descend the narrow field over their map.

        The expert's test, and where the vehicle stands within ``map_inflate`` of what it mapped (its inflated map has
        no way from there); the latter off with ``narrow_clearance`` 0, as the expert's narrow field is.
        """
        flat = super()._closed(env, slope)
        if not self._narrow:
            return flat
        a, b = self._map.cell(env.local_pos)
        return flat | (self._clear[np.arange(env.num_envs), a, b] <= self.ec.camera_map.map_inflate)

    def _phi(self, env: Any, ids: np.ndarray, anchor: np.ndarray, pts: np.ndarray, own: bool = True,
             rows: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        if rows is None:
            raise ValueError("expert_cammap: a field lookup without its flights")
        out = np.empty(len(rows))
        e1, e3 = np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
        values = self._fields_flat(own)
        trilinear_batch(np.asarray(rows, dtype=np.int64), np.ascontiguousarray(pts, dtype=np.float64), self._offset,
                        self._shape, self._origin, self._res, e1, e3, values, False, False, True, e1, e3,
                        out)  # fmt: skip
        return out

    def _fields_flat(self, own: bool) -> np.ndarray:
        """The flights' fields, flattened: the inflated map's (``own``), else the narrow one where it is built."""
        return self._phi_flat if own or not self._narrow else self._phi_narrow

    def _phi_fields(self, env: Any, ids: np.ndarray, anchor: np.ndarray, own: bool = True,
                    rows: np.ndarray | None = None) -> tuple:  # fmt: skip
        if rows is None:
            raise ValueError("expert_cammap: a field lookup without its flights")
        return (
            np.asarray(rows, dtype=np.int64),
            self._offset,
            self._shape,
            self._origin,
            self._res,
            self._fields_flat(own),
        )
