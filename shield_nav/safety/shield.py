"""The HOCBF safety shield: a real-time QP that projects each command onto a safe set built from the depth cloud.

Paper, "HOCBF-based Correction Loop". For the vehicle at position p with velocity v and an obstacle point o,
with r = p - o (from the obstacle point to the vehicle; derivation in docs/shield.md):

    B    = |r|^2 - r_safe^2
    Bdot = 2 r.v                      (o is static, so rdot = v)
    Bddot = 2 |v|^2 + 2 r.a
    HOCBF: Bddot + alpha1 Bdot + alpha0 B >= 0   <=>   2 r^T a >= -2|v|^2 - alpha1 Bdot - alpha0 B

The QP (paper's eq.) is a* = argmin 1/2 |a - a_raw|^2 subject to those rows for the K selected points and to a
polyhedral inner approximation of what the vehicle can fly (thrust range, tilt limit). The acceleration model is
a = f_n R(phi, theta, psi) e3 - g e3 (drag neglected). After the QP, a* is turned back into (f_n, phi, theta)
keeping the commanded yaw; a command that needs no correction is returned bit-for-bit unchanged.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import qpsolvers
import scipy.sparse as sp

from envs.camera import CameraConfig, depth_to_points
from shield_nav.safety.accel import _accel_from_command_1, _command_from_accel_1, accel_from_command, command_from_accel
from shield_nav.safety.fence import env_fence, fence_boxes, fence_points
from shield_nav.safety.memory import _append_remembered, _map_merge, _median_depth
from shield_nav.safety.rows import (
    _min_margin,
    _rows_min_margin,
    _select,
    backup_distance,
    backup_rows,
    braking_rows,
    ceiling_row,
    ground_row,
    hocbf_rows,
    passing_rows,
)
from shield_nav.safety.shield_config import (
    ShieldConfig,
)

__all__ = [
    "STATUS_FALLBACK",
    "STATUS_INACTIVE",
    "STATUS_NAMES",
    "STATUS_RELAXED",
    "STATUS_SOLVED",
    "HOCBFShield",
    "ShieldConfig",
    "ShieldOutput",
    "accel_from_command",
    "backup_distance",
    "backup_rows",
    "braking_rows",
    "ceiling_row",
    "command_from_accel",
    "env_fence",
    "fence_points",
    "ground_row",
    "hocbf_rows",
    "passing_rows",
]

STATUS_INACTIVE = 0
"""No selected constraint was violated by the raw command: returned unchanged, no QP solved."""
STATUS_SOLVED = 1
"""The hard-constrained QP was solved."""
STATUS_RELAXED = 2
"""The hard QP was infeasible; the slack-relaxed QP was solved (``slack`` > 0 reports by how much)."""
STATUS_FALLBACK = 3
"""Both QPs failed (solver error): a braking command within the actuator limits was returned."""
STATUS_NAMES = {0: "inactive", 1: "solved", 2: "relaxed", 3: "fallback"}
_E3 = np.array([[0.0, 0.0, 1.0]])
_NEG_E3 = -_E3
_NO_ROWS, _NO_RHS = np.zeros((0, 3)), np.zeros(0)
_PLANE_EPS = 1.0e-3  # [m/s^2] an altitude row's right-hand side stays this far inside the actuator range
_ZERO3 = np.zeros(3)
_EMPTY_POINTS = np.zeros((0, 3))  # a vehicle's local map before its first intake
_EMPTY_STAMPS = np.zeros(0, dtype=np.int64)
_EYE3 = np.eye(3)


# --------------------------------------------------------------------------------------------- the shield
@dataclass
class ShieldOutput:
    """Result of one batched shield call. Every array has a leading N."""

    command: np.ndarray
    """Corrected commands (N, 4) = [f_n, phi, theta, psi]; bit-identical to the input where inactive."""
    accel_raw: np.ndarray
    """Acceleration of the raw command (N, 3) [m/s^2]."""
    accel_safe: np.ndarray
    """Acceleration after the QP (N, 3) [m/s^2]."""
    active: np.ndarray
    """(N,) bool: the shield changed the command."""
    status: np.ndarray
    """(N,) int: one of STATUS_* (inactive, solved, relaxed, fallback)."""
    num_constraints: np.ndarray
    """(N,) int: obstacle constraints in the QP (the ground and ceiling rows, when on, are not counted)."""
    slack: np.ndarray
    """(N,) float: relaxation slack used (0 unless relaxed)."""
    solve_us: np.ndarray
    """(N,) float: time spent in the QP solver calls [us] (0 when inactive)."""
    total_us: np.ndarray
    """(N,) float: whole per-vehicle shield time [us]: point cloud, selection, QP, conversion back."""
    choice: np.ndarray | None = None
    """(N,) int: which command was filtered, 0 the given ``command``, j >= 1 ``alternatives[:, j - 1]``."""


class HOCBFShield:
    """Batched HOCBF safety filter. See the module docstring for the math and docs/shield.md for the derivation.

    Args:
        cfg: shield parameters.
        camera: the depth camera's configuration (to back-project depth images to world points).
    """

    def __init__(self, cfg: ShieldConfig | None = None, camera: CameraConfig | None = None) -> None:  # noqa: D107
        self.cfg = cfg = cfg if cfg is not None else ShieldConfig()
        cfg.validate()
        self.camera = camera if camera is not None else CameraConfig()
        self._memory: dict[int, np.ndarray] = {}  # vehicle id -> (memory_steps * K, 3) ring of points (NaN: empty)
        self._memory_head: dict[int, int] = {}
        self._prev_vel: dict[int, np.ndarray] = {}  # vehicle id -> velocity at its previous call (lag_s)
        self._map: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # vehicle id -> local map: points (M, 3), call stamps
        self._map_calls: dict[int, int] = {}  # vehicle id -> calls since its reset (map_seconds)
        self._depth_buf: np.ndarray | None = None  # the filtered image (depth_filter), reused per call
        # One image's points followed by the remembered ones, written in place (no per-step allocation or copy).
        cam = self.camera
        self._cloud = np.empty((cam.height * cam.width + cfg.memory_steps * cfg.max_constraints, 3))
        self._r_buf = np.zeros((cfg.max_constraints, 3))
        self._b_buf = np.zeros(cfg.max_constraints)
        self._min_buf = np.zeros(1)
        self._o_buf = np.zeros((cfg.max_constraints, 3))  # the selected obstacle points
        self._row_buf = np.zeros(4)  # the tightest row of the active-set check: r (3), b
        self._rows = np.zeros((0, 8))  # braking barrier: every considered point's rows from the last selection
        self._rows_n = np.zeros(1, dtype=np.int64)  # how many (-1: none kept, the distance barrier)
        self._a_buf = np.zeros(3)
        # (braking-type rows, a_b, gain, mode: 0 braking, 1 braking + collision cone, 2 backup; see _consts)
        self._brake_params = np.array([0.0 if cfg.barrier == "distance" else 1.0, cfg.brake_accel, cfg.brake_gain,
                                       2.0 if cfg.barrier == "backup" else (1.0 if cfg.passing else 0.0)])  # fmt: skip
        self._g = np.array([0.0, 0.0, cfg.gravity])
        # Actuator limits on T = a + g e3, written as G_act a <= h_act:
        #   tilt: n_k . T_xy <= tan(max_tilt) cos(pi / F) T_z  for F face normals n_k (inscribed polygon),
        #   thrust: T_z >= f_min (a subset of |T| >= f_min), and |T| <= f_max through the inscribed facets
        #   d_j . T <= f_max cos(delta), with d_j covering the tilt cone (delta: worst angle to the nearest d_j).
        tan_t = math.tan(math.radians(cfg.max_tilt_deg)) * math.cos(math.pi / cfg.tilt_faces)
        rows, rhs = [], []
        for k in range(cfg.tilt_faces):
            ang = 2 * math.pi * (k + 0.5) / cfg.tilt_faces
            n = np.array([math.cos(ang), math.sin(ang), -tan_t])
            rows.append(n)
            rhs.append(-(n @ self._g))  # n . (a + g e3) <= 0
        rows.append(np.array([0.0, 0.0, -1.0]))
        rhs.append(cfg.gravity - cfg.thrust_range[0])  # -(a_z + g) <= -f_min
        dirs = self._cap_directions(math.radians(cfg.max_tilt_deg))
        delta = self._coverage(dirs, math.radians(cfg.max_tilt_deg))
        for d in dirs:
            rows.append(d)
            rhs.append(cfg.thrust_range[1] * math.cos(delta) - d @ self._g)
        self._g_act = np.array(rows)
        self._h_act = np.array(rhs)
        self.thrust_cap_scale = math.cos(delta)
        """Fraction of f_max reachable in the worst direction under the inscribed thrust facets."""
        # Vertical acceleration range with a level attitude (inside the polytope above).
        self._az_min = cfg.thrust_range[0] - cfg.gravity
        self._az_max = cfg.thrust_range[1] * math.cos(delta) - cfg.gravity
        self._sparse = cfg.solver in ("osqp", "scs", "clarabel")
        # OSQP's defaults (eps 1e-3) leave ~5e-3 m/s^2 errors; tighten them and polish to active-set accuracy.
        osqp_opts = {"eps_abs": 1e-7, "eps_rel": 1e-7, "polishing": True, "raise_error": False}
        self._solver_opts = osqp_opts if cfg.solver == "osqp" else {}

    @staticmethod
    def _cap_directions(max_tilt: float) -> np.ndarray:
        """Unit directions covering the cone of tilts <= max_tilt: the vertical plus rings of 8 at 1/3 and 2/3."""
        out = [np.array([0.0, 0.0, 1.0])]
        for frac, count in ((1.0 / 3.0, 6), (2.0 / 3.0, 10), (1.0, 14)):
            tilt = frac * max_tilt
            for k in range(count):
                az = 2 * math.pi * k / count
                out.append(np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)]))
        return np.array(out)

    @staticmethod
    def _coverage(dirs: np.ndarray, max_tilt: float) -> float:
        """Largest angle from any direction in the tilt cone to its nearest d_j (dense sampling, plus 10 %)."""
        tilt, az = np.meshgrid(np.linspace(0, max_tilt, 60), np.linspace(0, 2 * math.pi, 241))
        u = np.stack((np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)), axis=-1).reshape(-1, 3)
        worst = np.arccos(np.clip((u @ dirs.T).max(axis=1), -1, 1)).max()
        return float(min(1.1 * worst, math.radians(30.0)))

    # ------------------------------------------------------------------------------ single vehicle
    def constraints(
        self,
        points_w: np.ndarray,
        pos_w: np.ndarray,
        vel_w: np.ndarray,
        accel_raw: np.ndarray,
        lagged: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Select up to K points and return (r (k, 3), A (k, 3), b (k,)) with rows A a >= b.

        ``lagged``: (position, velocity) predicted one lag ahead (``lag_s``); each point then also has its row at
        that state, and keeps the tighter of the two. ``r`` is the offset of the state its row was taken at, i.e. A / 2
        (with ``passing``, a collision-cone row has A / 2 = (r + S v / |v|) / 2 instead; ``passing_rows``).
        """
        c = self.cfg
        pts = np.ascontiguousarray(points_w, dtype=np.float64).reshape(-1, 3)
        p = np.asarray(pos_w, dtype=np.float64)
        v = np.asarray(vel_w, dtype=np.float64)
        p_lag, v_lag = (p, v) if lagged is None else (np.asarray(x, dtype=np.float64) for x in lagged)
        if c.barrier != "distance" and len(self._rows) < len(pts):
            self._rows = np.empty((max(len(pts), 2 * len(self._rows)), 8))
        n = _select(
            pts, p, v, p_lag, v_lag, lagged is not None,
            np.asarray(accel_raw, dtype=np.float64), c.alpha0, c.alpha1, c.r_safe, c.point_filter[0],
            c.point_filter[1], c.z_window[0], c.z_window[1], c.azimuth_sectors, c.elevation_sectors,
            c.max_constraints, self._r_buf, self._b_buf, self._min_buf, self._o_buf, self._brake_params,
            self._rows, self._rows_n,
        )  # fmt: skip
        r = self._r_buf[:n].copy()
        return r, 2.0 * r, self._b_buf[:n].copy()

    def min_margin(
        self,
        points_w: np.ndarray,
        pos_w: np.ndarray,
        vel_w: np.ndarray,
        accel: np.ndarray,
        lagged: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> float:
        """Smallest HOCBF row value at ``accel`` over every point (inf if none): negative means a row is broken.

        The tightest row is left in ``self._row_buf`` as (r, b).
        """
        c = self.cfg
        pts = np.ascontiguousarray(points_w, dtype=np.float64).reshape(-1, 3)
        p = np.asarray(pos_w, dtype=np.float64)
        v = np.asarray(vel_w, dtype=np.float64)
        p_lag, v_lag = (p, v) if lagged is None else (np.asarray(x, dtype=np.float64) for x in lagged)
        return _min_margin(
            pts, p, v, p_lag, v_lag, lagged is not None, np.asarray(accel, dtype=np.float64), c.alpha0, c.alpha1,
            c.r_safe, c.point_filter[0], c.point_filter[1], c.z_window[0], c.z_window[1], self._row_buf,
            self._brake_params,
        )  # fmt: skip

    def _plane_rows(self, z: float, v_z: float) -> tuple[np.ndarray, np.ndarray]:
        """The altitude rows (ground, ceiling) that are on, as (A (k, 3), b (k,)) with A a >= b.

        A right-hand side beyond what the actuators can give (a climb too fast to stop under the ceiling with
        minimum thrust, a descent too fast to stop above the ground with maximum thrust) is capped at the largest
        achievable value: the row then asks for the hardest vertical braking there is, and stays feasible.
        """
        c = self.cfg
        rows, rhs = [], []
        if c.min_altitude > 0:
            rows.append(_E3[0])
            rhs.append(min(ground_row(z, v_z, c.alpha0, c.alpha1, c.min_altitude), self._az_max - _PLANE_EPS))
        if c.max_altitude > 0:
            rows.append(_NEG_E3[0])
            rhs.append(min(ceiling_row(z, v_z, c.alpha0, c.alpha1, c.max_altitude), -self._az_min - _PLANE_EPS))
        if not rows:
            return _NO_ROWS, _NO_RHS
        return np.array(rows), np.array(rhs)

    def solve(
        self,
        accel_raw: np.ndarray,
        a_mat: np.ndarray,
        b_vec: np.ndarray,
        vel_w: np.ndarray,
        plane_mat: np.ndarray | None = None,
        plane_vec: np.ndarray | None = None,
    ) -> tuple[np.ndarray, int, float, float]:
        """Project accel_raw (3,) onto {A a >= b} intersected with the actuator polytope.

        ``plane_mat``/``plane_vec`` are the altitude rows (ground, ceiling) in the same form; they stay hard when
        the obstacle rows are relaxed (their right-hand sides are within the actuator range, so they never make
        the relaxed problem infeasible). Returns (a*, status, slack, solver_us). ``status`` is STATUS_SOLVED,
        STATUS_RELAXED or STATUS_FALLBACK.
        """
        c = self.cfg
        if plane_vec is None or len(plane_vec) == 0:
            hard_g, hard_h = self._g_act, self._h_act  # the default: no altitude rows, nothing to stack
        else:
            hard_g = np.vstack((-plane_mat, self._g_act))
            hard_h = np.concatenate((-plane_vec, self._h_act))
        g_mat = np.vstack((-a_mat, hard_g))
        h_vec = np.concatenate((-b_vec, hard_h))
        t0 = time.perf_counter()
        w = self._metric(vel_w)
        q = -accel_raw if w is _EYE3 else -(w @ accel_raw)  # the default skips the product
        x = self._qp(w, q, g_mat, h_vec)
        if x is not None and np.all(np.isfinite(x)):
            return x, STATUS_SOLVED, 0.0, 1e6 * (time.perf_counter() - t0)
        # Relaxed: variables [a, s]; obstacle rows A a + s >= b, s >= 0; altitude rows and actuator limits hard;
        # cost 1/2 (a - a_raw)^T W (a - a_raw) + slack_weight/2 s^2 (W = I unless the correction metric is set).
        k = len(b_vec)
        p4 = np.diag([1.0, 1.0, 1.0, c.slack_weight])
        p4[:3, :3] = w
        q4 = np.concatenate((q, [0.0]))
        g4 = np.zeros((k + len(hard_h) + 1, 4))
        g4[:k, :3] = -a_mat
        g4[:k, 3] = -1.0
        g4[k : k + len(hard_h), :3] = hard_g
        g4[-1, 3] = -1.0
        h4 = np.concatenate((-b_vec, hard_h, [0.0]))
        x = self._qp(p4, q4, g4, h4)
        us = 1e6 * (time.perf_counter() - t0)
        if x is not None and np.all(np.isfinite(x)):
            return x[:3], STATUS_RELAXED, float(max(x[3], 0.0)), us
        # Fallback: brake along -v at the largest decelaration the tilt limit allows, hold altitude.
        return self._brake(vel_w), STATUS_FALLBACK, math.inf, us

    def _metric(self, vel_w: np.ndarray) -> np.ndarray:
        """The QP's cost matrix W (3, 3), positive definite: identity unless along/vertical weights are set."""
        c = self.cfg
        if c.along_weight == 1.0 and c.vertical_weight == 1.0:
            return _EYE3
        w = np.eye(3)
        w[2, 2] = c.vertical_weight
        vh = np.array([vel_w[0], vel_w[1], 0.0])
        # u u^T scaled by min(|v_h|^2, 1) / |v_h|^2: the along-weight fades in over the first 1 m/s.
        w += (c.along_weight - 1.0) * np.outer(vh, vh) / max(float(vh @ vh), 1.0)
        return w

    def _qp(self, p: np.ndarray, q: np.ndarray, g: np.ndarray, h: np.ndarray) -> np.ndarray | None:
        if self._sparse:
            p, g = sp.csc_matrix(p), sp.csc_matrix(g)
        try:
            return qpsolvers.solve_qp(p, q, g, h, solver=self.cfg.solver, **self._solver_opts)
        except Exception:  # a solver error must never abort a flight: the caller falls back
            return None

    def _brake(self, vel_w: np.ndarray) -> np.ndarray:
        """A flyable braking acceleration: a = -2 v, horizontally <= 0.8 g tan(max_tilt), vertically <= g/2."""
        a = -2.0 * np.asarray(vel_w, dtype=np.float64)
        cap = 0.8 * self.cfg.gravity * math.tan(math.radians(self.cfg.max_tilt_deg))
        h = math.hypot(a[0], a[1])
        if h > cap:
            a[:2] *= cap / h
        a[2] = min(max(a[2], -0.5 * self.cfg.gravity), 0.5 * self.cfg.gravity)
        return a

    def reset(self, ids: np.ndarray | None = None) -> None:
        """Forget the point memory of vehicle ``ids`` (all if None); call it when a vehicle starts a new episode."""
        if ids is None:
            self._memory.clear()
            self._memory_head.clear()
            self._prev_vel.clear()
            self._map.clear()
            self._map_calls.clear()
        else:
            for i in np.atleast_1d(ids):
                self._memory.pop(int(i), None)
                self._memory_head.pop(int(i), None)
                self._prev_vel.pop(int(i), None)
                self._map.pop(int(i), None)
                self._map_calls.pop(int(i), None)

    def _remember(self, vid: int, points: np.ndarray) -> None:
        """Store the obstacle points of this step's constraints in vehicle ``vid``'s ring."""
        k = self.cfg.max_constraints
        ring = self._memory.get(vid)
        if ring is None:
            ring = self._memory[vid] = np.full((self.cfg.memory_steps * k, 3), np.nan)
            self._memory_head[vid] = 0
        head = self._memory_head[vid]
        ring[head * k : (head + 1) * k] = np.nan
        ring[head * k : head * k + len(points)] = points
        self._memory_head[vid] = (head + 1) % self.cfg.memory_steps

    def _filtered(self, depth: np.ndarray) -> np.ndarray:
        """One depth image (any shape of H x W pixels) through ``depth_filter``, into a buffer reused per call."""
        cam = self.camera
        d = np.asarray(depth).reshape(cam.height, cam.width)
        if self._depth_buf is None or self._depth_buf.dtype != d.dtype:
            self._depth_buf = np.empty((cam.height, cam.width), dtype=d.dtype)
        _median_depth(d, self._depth_buf, self.cfg.depth_filter == "median_3x3")
        return self._depth_buf

    def map_points(self, vid: int) -> np.ndarray:
        """The points (M, 3) of vehicle ``vid``'s local map (``map_seconds`` > 0); empty if it has none."""
        m = self._map.get(int(vid))
        return np.zeros((0, 3)) if m is None else m[0].copy()

    def _with_map(self, vid: int, pts: np.ndarray, n_img: int, p: np.ndarray, in_cloud: bool) -> np.ndarray:
        """Merge this call's image points (``pts[:n_img]``) into ``vid``'s local map when due; the cloud plus the map.

        The intake takes the image's points within ``map_radius`` of ``p`` and inside ``z_window``; the merged set
        keeps one point per ``map_voxel`` cube, the newest, in cube-key order, and drops what is older than
        ``map_seconds`` or beyond ``map_radius`` (``rows._map_merge``). ``in_cloud``: ``pts`` is the first
        rows of ``self._cloud``, so the map's points are written after them in place (the buffer grows if needed).
        """
        cfg = self.cfg
        calls = self._map_calls.get(vid, 0)
        self._map_calls[vid] = calls + 1
        m = self._map.get(vid)
        if calls % cfg.map_every == 0:
            old, old_st = m if m is not None else (_EMPTY_POINTS, _EMPTY_STAMPS)
            m = self._map[vid] = _map_merge(
                np.ascontiguousarray(pts[:n_img]), old, old_st, p, cfg.map_radius * cfg.map_radius, cfg.z_window[0],
                cfg.z_window[1], calls, round(cfg.map_seconds / cfg.control_dt), cfg.map_voxel,
            )  # fmt: skip
        if m is None or not len(m[0]):
            return pts
        if not in_cloud:
            return np.concatenate((pts, m[0]))
        n, k = len(pts), len(m[0])
        if n + k > len(self._cloud):
            grown = np.empty((max(n + k, 2 * len(self._cloud)), 3))
            grown[:n] = self._cloud[:n]
            self._cloud = grown
        self._cloud[n : n + k] = m[0]
        return self._cloud[: n + k]

    # ------------------------------------------------------------------------------ batched
    def filter_env(self, env, command: np.ndarray, ids: np.ndarray | None = None,  # noqa: ANN001
                   alternatives: np.ndarray | None = None) -> ShieldOutput:  # fmt: skip
        """Filter the commands (len(ids), 4) of a ``NavigationEnv``'s vehicles ``ids`` (all if None) on its state.

        The state is the sensor's depth image with the body attitude, the env-local position and the velocity. The
        evaluation's shielded rows and the shield in the training loop both call this, so they filter alike.
        """
        sel = slice(None) if ids is None else ids
        fence = env_fence(env)[sel] if self.cfg.fence else None
        return self.filter(command, env.local_pos[sel], env.vehicles.vel_w[sel], depth=env.sensor_depth_buf[sel],
                           R_wb=env.vehicles.R_wb[sel], ids=ids, alternatives=alternatives, fence=fence)  # fmt: skip

    def filter(
        self,
        command: np.ndarray,
        pos_w: np.ndarray,
        vel_w: np.ndarray,
        depth: np.ndarray | None = None,
        R_wb: np.ndarray | None = None,  # noqa: N803
        points_w: list[np.ndarray] | None = None,
        ids: np.ndarray | None = None,
        alternatives: np.ndarray | None = None,
        fence: np.ndarray | None = None,
    ) -> ShieldOutput:
        """Filter N commands (N, 4). Obstacles come from depth images (N, 1, H, W) with body poses, or point lists.

        Vehicle state: ``pos_w`` (N, 3), ``vel_w`` (N, 3). For depth input, ``R_wb`` (N, 3, 3) is the body
        attitude when the image was taken (the camera mount comes from the camera config). ``ids`` (N,) names
        the vehicles for the point memory (``memory_steps`` > 0) and the previous acceleration (``lag_s`` > 0) when
        the batch is a changing subset; default 0..N-1. ``alternatives`` (N, J, 4): a multi-hypothesis policy's
        other candidates in its score order, used as :attr:`ShieldConfig.hypotheses` says (ignored with ``"top"``);
        the output's ``choice`` says which command each vehicle flew. ``fence`` (N, 2, 2) or (2, 2): each vehicle's
        geofence ``[[x_lo, y_lo], [x_hi, y_hi]]`` in the frame of ``pos_w``, required when
        :attr:`ShieldConfig.fence` is on and refused when it is off.
        """
        cmd = np.atleast_2d(np.asarray(command, dtype=np.float64))
        num = len(cmd)
        if (depth is None) == (points_w is None):
            raise ValueError("give exactly one of depth (with R_wb) or points_w")
        if not np.all(np.isfinite(cmd)):
            bad = np.flatnonzero(~np.isfinite(cmd).all(axis=1)).tolist()
            raise ValueError(f"non-finite command for vehicle index(es) {bad}")
        alts = None
        if alternatives is not None and self.cfg.hypotheses != "top":
            alts = np.asarray(alternatives, dtype=np.float64)
            if alts.ndim != 3 or alts.shape[0] != num or alts.shape[2] != 4:
                raise ValueError(f"alternatives must be (N, J, 4) with N = {num}, got shape {alts.shape}")
            if not np.all(np.isfinite(alts)):
                bad = np.flatnonzero(~np.isfinite(alts).all(axis=(1, 2))).tolist()
                raise ValueError(f"non-finite alternative command for vehicle index(es) {bad}")
        fence_box = fence_boxes(fence, num, self.cfg.fence, self.cfg.fence_inset)
        choice = np.zeros(num, dtype=np.int64)
        out_cmd = cmd.copy()
        g = self.cfg.gravity
        a_raw = np.empty((num, 3))
        a_safe = np.empty((num, 3))
        active = np.zeros(num, dtype=bool)
        status = np.zeros(num, dtype=np.int64)
        ncon = np.zeros(num, dtype=np.int64)
        slack = np.zeros(num)
        solve_us = np.zeros(num)
        total_us = np.zeros(num)
        lag = self.cfg.lag_s
        for i in range(num):
            # Everything a deployed vehicle would run per control step is inside the timed region.
            t0 = time.perf_counter()
            _accel_from_command_1(cmd[i, 0], cmd[i, 1], cmd[i, 2], cmd[i, 3], g, self._a_buf)
            a_raw[i] = self._a_buf
            vid = int(ids[i]) if ids is not None else i
            ring = self._memory.get(vid) if self.cfg.memory_steps > 0 else None
            in_cloud = depth is not None and not self.cfg.voxel  # pts: the first rows of self._cloud
            img = depth[i] if depth is not None else None
            if img is not None and self.cfg.depth_filter != "none":
                img = self._filtered(img)
            if in_cloud:
                pts = depth_to_points(img, pos_w[i], R_wb[i], self.camera, out=self._cloud)
                n_img = len(pts)
                if ring is not None:  # the remembered points go right after the image's, in the same buffer
                    pts = self._cloud[: _append_remembered(ring, self._cloud, len(pts))]
            else:
                if depth is not None:
                    pts = depth_to_points(img, pos_w[i], R_wb[i], self.camera, self.cfg.voxel)
                else:
                    pts = np.asarray(points_w[i], dtype=np.float64).reshape(-1, 3)
                n_img = len(pts)
                if ring is not None:
                    pts = np.concatenate((pts, ring[~np.isnan(ring[:, 0])]))
            p_i, v_i = pos_w[i], vel_w[i]
            if self.cfg.map_seconds > 0.0:
                pts = self._with_map(vid, pts, n_img, np.asarray(p_i, dtype=np.float64), in_cloud)
            lagged = None
            if lag > 0.0:
                # The state the command will act on: the vehicle keeps its current acceleration for one lag.
                v_prev = self._prev_vel.get(vid)
                a0 = _ZERO3 if v_prev is None else (v_i - v_prev) / self.cfg.control_dt
                self._prev_vel[vid] = np.array(v_i, dtype=np.float64)
                lagged = (p_i + lag * v_i + 0.5 * lag * lag * a0, v_i + lag * a0)
            if fence_box is not None:
                rng = self.cfg.point_filter[1]
                walls = [fence_points(p_i, fence_box[i], rng)]
                if lagged is not None:
                    walls.append(fence_points(lagged[0], fence_box[i], rng))
                pts = np.concatenate((pts, *walls))
            if alts is not None:
                k = self._pick_hypothesis(cmd[i], alts[i], pts, p_i, v_i, lagged)
                if k > 0:
                    choice[i] = k
                    out_cmd[i] = alts[i, k - 1]
                    _accel_from_command_1(alts[i, k - 1, 0], alts[i, k - 1, 1], alts[i, k - 1, 2], alts[i, k - 1, 3],
                                          g, self._a_buf)  # fmt: skip
                    a_raw[i] = self._a_buf
                else:  # the screening overwrote the buffer: back to the policy's own command
                    _accel_from_command_1(cmd[i, 0], cmd[i, 1], cmd[i, 2], cmd[i, 3], g, self._a_buf)
            r_sel, a_mat, b_vec = self.constraints(pts, p_i, v_i, self._a_buf, lagged)
            if self.cfg.memory_steps > 0:
                self._remember(vid, self._o_buf[: len(r_sel)])
            ncon[i] = len(b_vec)
            violated = len(b_vec) > 0 and self._min_buf[0] < 0.0  # smallest margin A a_raw - b < 0
            plane_mat, plane_vec = self._plane_rows(p_i[2], v_i[2])
            if len(plane_vec):
                violated = violated or bool(np.any(plane_mat @ self._a_buf < plane_vec))
            if violated:
                a_star, status[i], slack[i], solve_us[i] = self.solve(a_raw[i], a_mat, b_vec, v_i, plane_mat, plane_vec)
                for _ in range(self.cfg.active_set_iterations if status[i] == STATUS_SOLVED else 0):
                    # Check every point at a*; add the most violated row if any is broken, and re-solve.
                    if self._rows_n[0] >= 0:  # braking rows kept by the selection: the same numbers, cheaper
                        worst = _rows_min_margin(self._rows, int(self._rows_n[0]), a_star, self._row_buf)
                    else:
                        worst = self.min_margin(pts, p_i, v_i, a_star, lagged)
                    if worst >= -self.cfg.active_set_tol:
                        break
                    a_mat = np.vstack((a_mat, 2.0 * self._row_buf[None, :3]))
                    b_vec = np.append(b_vec, self._row_buf[3])
                    a_star, status[i], slack[i], us = self.solve(a_raw[i], a_mat, b_vec, v_i, plane_mat, plane_vec)
                    solve_us[i] += us
                    ncon[i] = len(b_vec)
                    if status[i] != STATUS_SOLVED:
                        break
                a_safe[i] = a_star
                out_cmd[i, :3] = _command_from_accel_1(a_star[0], a_star[1], a_star[2], out_cmd[i, 3], g)
                active[i] = True
            else:
                a_safe[i] = a_raw[i]
            total_us[i] = 1e6 * (time.perf_counter() - t0)
        return ShieldOutput(out_cmd, a_raw, a_safe, active, status, ncon, slack, solve_us, total_us, choice)

    def _pick_hypothesis(
        self,
        command: np.ndarray,
        alternatives: np.ndarray,
        pts: np.ndarray,
        p: np.ndarray,
        v: np.ndarray,
        lagged: tuple[np.ndarray, np.ndarray] | None,
    ) -> int:
        """Index into [command, *alternatives] that :attr:`ShieldConfig.hypotheses` flies (0: ``command``).

        A candidate is clean when its acceleration keeps every point's row (at the state and, with ``lag_s``, one
        lag ahead) and the altitude rows. Uses ``self._a_buf`` as scratch.
        """
        g = self.cfg.gravity
        plane_mat, plane_vec = self._plane_rows(p[2], v[2])
        best_k, best_m = 0, -math.inf
        for k in range(len(alternatives) + 1):
            c = command if k == 0 else alternatives[k - 1]
            _accel_from_command_1(c[0], c[1], c[2], c[3], g, self._a_buf)
            m = self.min_margin(pts, p, v, self._a_buf, lagged) if len(pts) else math.inf
            if len(plane_vec):
                m = min(m, float(np.min(plane_mat @ self._a_buf - plane_vec)))
            if m >= 0.0:
                return k
            if m > best_m:
                best_k, best_m = k, m
        return best_k if self.cfg.hypotheses == "safest" else 0
