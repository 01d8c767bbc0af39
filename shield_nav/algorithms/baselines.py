"""Baseline controllers that need no learned weights, run through the same evaluation harness as the policies.

Every controller maps the env's current state to vehicle commands ``[f_n, phi, theta, psi]`` (N, 4), which the
harness flies with ``env.step(actions, commands=...)`` (after the HOCBF shield where a row asks for it):

* :class:`OracleController`: follows the descent of the privileged geodesic (Dijkstra) field with a velocity
  tracking controller and an ESDF repulsion. It reads the map, so it is **privileged**: an upper bound for what a
  reactive policy flying the same vehicle could do, not a fair competitor.
* :class:`ReactivePlanner`: a classical depth-only planner. It back-projects the current depth image to a point
  cloud, scores a fan of straight motion primitives for collision (free distance along each) and goal progress,
  flies the best at a speed it can stop within, and brakes and turns when nothing is free.
* :class:`GoalSeeker`: flies straight at the goal at the target speed. Alone it measures how cluttered a scene is;
  with the shield ("shield only") it isolates what the HOCBF filter achieves without a learned policy.

All three share :func:`accel_to_command`, which turns a desired world-frame acceleration into a flyable command
with the shield's acceleration model ``a = f_n R(phi, theta, psi) e3 - g e3`` (drag neglected).
"""

from __future__ import annotations

import math
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from envs.camera import depth_to_points
from envs.config import require
from shield_nav.algorithms.expert import PlannerController
from shield_nav.algorithms.expert_cammap import CameraMapPlanner
from shield_nav.algorithms.expert_config import ExpertConfig
from shield_nav.algorithms.tracking import TrackingConfig, accel_to_command
from shield_nav.safety.camera_map import CameraMap
from shield_nav.safety.escape import EscapeConfig


@dataclass
class OracleConfig:
    """Privileged geodesic-descent oracle."""

    guidance: str = "geodesic"
    """Potential the oracle descends: ``geodesic`` (the Dijkstra field Phi, around obstacles) or ``euclidean`` (the
    straight-line distance to the episode's goal point, the potential of the paper's Distance reward). Repulsion
    and slow-down are the same for both, so the two differ only in their global guidance."""
    lookahead_s: float = 0.3
    """The descent direction is read at p + v * lookahead_s (anticipates turns) [s]."""
    repulse_dist: float = 0.8
    """ESDF below which a repulsion along grad(ESDF) is added [m]."""
    repulse_gain: float = 3.0
    """Repulsion velocity per metre of ESDF deficit [1/s]."""
    slow_dist: float = 0.6
    """Speed is scaled by clip(ESDF_ahead / slow_dist, min_speed_fraction, 1) [m]."""
    min_speed_fraction: float = 0.5
    """Lower bound of that speed scale."""
    fd_step: float = 0.2
    """Central-difference step of the geodesic gradient [m]."""
    goal_switch: float = 3.0
    """Below this geodesic distance to the goal region, fly straight at the goal point instead [m]. (The field
    flows to the whole 1 x 32 m goal box; success needs the goal point within 5 m.)"""
    episode_goal: bool = False
    """Descend the geodesic field of the episode's own goal anchor (``env.episode.goal_anchors`` > 0 with the
    geodesic reward) instead of the whole goal region's field; falls back to the region field when the env has no
    anchor fields. The expert of the oracle-DAgger student uses it (it leads to the goal point itself); the
    evaluation rows keep the region field their published numbers were measured with."""
    field_radius: float = 0.0
    """> 0: descend geodesic fields the oracle builds itself (region and goal anchors, cached on disk like the
    env's), with obstacles inflated by this radius [m] instead of the env's vehicle radius (0.2 m). The shortest
    paths then keep this clearance, and inside the inflated margin the field's values (nearest traversable node +
    distance to it) lead back out. 0: the env's own fields."""

    def validate(self, prefix: str = "") -> None:
        """A known guidance."""
        require(self.guidance in ORACLE_GUIDANCE, f"{prefix}guidance",
                f"unknown guidance {self.guidance!r}; expected one of {ORACLE_GUIDANCE}")  # fmt: skip


ORACLE_GUIDANCE = ("geodesic", "euclidean")
"""Potentials the oracle can descend (:attr:`OracleConfig.guidance`)."""
REACTIVE_GUIDANCE = (*ORACLE_GUIDANCE, "map")
"""Directions the reactive planner aligns with (:attr:`ReactiveConfig.guidance`)."""


@dataclass
class ReactiveConfig:
    """Depth-only motion-primitive planner."""

    azimuths_deg: list[float] = field(default_factory=lambda: [-40, -30, -20, -12, -6, 0, 6, 12, 20, 30, 40])
    """Primitive directions relative to the current heading [deg] (inside the camera's 87 deg field of view)."""
    elevations_deg: list[float] = field(default_factory=lambda: [-12.0, 0.0, 12.0])
    """Primitive climb angles [deg]."""
    horizon: float = 8.0
    """Primitive length [m] (free distances are capped here)."""
    collision_radius: float = 0.5
    """A point closer than this to a primitive's line blocks it [m] (vehicle 0.2 m + margin)."""
    min_free: float = 1.5
    """Primitives whose free distance is shorter than this are rejected [m]."""
    brake_accel: float = 5.0
    """Deceleration used for the stop-within-free-distance speed rule v = sqrt(2 a (free - stop_margin)) [m/s^2]."""
    stop_margin: float = 1.0
    """Distance kept in reserve by that rule [m]."""
    w_goal: float = 1.0
    """Weight of goal alignment cos(angle(d, goal)) in the score."""
    w_free: float = 0.6
    """Weight of the free distance (normalised by the horizon) in the score."""
    w_smooth: float = 0.2
    """Weight of the change from the previous primitive (|d - d_prev|) in the score (a penalty)."""
    voxel: float = 0.2
    """Point cloud voxel edge [m]."""
    replan_every: int = 5
    """Replan every this many control steps (20 Hz at 100 Hz control); the chosen primitive is held in between."""
    search_turn_deg: float = 35.0
    """When no primitive is free: brake and turn the heading by this much towards the goal side [deg]."""
    guidance: str = "euclidean"
    """Goal direction the score aligns with: ``euclidean`` (straight at the goal point; depth only, the published
    row), ``geodesic`` (-grad Phi at the vehicle, read from the privileged geodesic field like the oracle's: the
    ``reactive_geodesic`` row) or ``map`` (towards the point ``camera_map.lookahead`` metres along a Dijkstra plan
    over the 2D map of what the flight's own camera has shown, unmapped space free, replanned every
    ``camera_map.replan_s``: the ``reactive_map`` row, depth only). Same local avoidance, different global
    guidance."""
    camera_map: EscapeConfig = field(default_factory=lambda: EscapeConfig(kind="map"))
    """``guidance: map``: the map and its plan (:class:`shield_nav.safety.camera_map.CameraMap`); only its ``map_*``
    keys, ``replan_s``, ``lookahead`` and ``goal_radius`` are read."""

    def validate(self, prefix: str = "") -> None:
        """A known guidance and a valid map."""
        require(self.guidance in REACTIVE_GUIDANCE, f"{prefix}guidance",
                f"unknown guidance {self.guidance!r}; expected one of {REACTIVE_GUIDANCE}")  # fmt: skip
        self.camera_map.validate(f"{prefix}camera_map.")


@dataclass
class BaselineConfig:
    """Parameters of every baseline."""

    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    """Velocity tracking."""
    oracle: OracleConfig = field(default_factory=OracleConfig)
    """Geodesic oracle."""
    reactive: ReactiveConfig = field(default_factory=ReactiveConfig)
    """Reactive depth planner."""
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    """Privileged planning expert (:mod:`shield_nav.algorithms.expert`)."""


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _heading(r_wb: np.ndarray) -> np.ndarray:
    """Yaw (N,) of body-to-world rotations (N, 3, 3) (ZYX convention: psi = atan2(R10, R00))."""
    return np.arctan2(r_wb[:, 1, 0], r_wb[:, 0, 0])


class MapGuide:
    """Guidance from the map of what each flight's own camera has shown (the reactive planner's ``guidance: map``).

    At control steps that are multiples of ``map_every`` it marks the flights' depth images in a
    :class:`shield_nav.safety.camera_map.CameraMap`; every ``replan_s`` it replans each flight's Dijkstra over that map
    (unmapped space free) and keeps the point ``lookahead`` metres along it. The guide is the unit direction to that
    point horizontally and to the goal's height vertically, or straight at the goal where the plan reaches the goal
    region. Reads nothing privileged.
    """

    def __init__(self, cfg: EscapeConfig, env: Any, pool: Executor | None = None) -> None:  # noqa: D107
        self.map = CameraMap.for_env(cfg, env)
        self.target = np.full((env.num_envs, 2), np.nan)
        self.delay = int(cfg.plan_delay_steps)
        self.pool = pool  # with a delay: the plans run there (a vehicle's planning thread); None: inline
        self._pending: list[tuple[int, int, Any]] = []  # (step it is flown from, flight, Future or result)

    def __call__(
        self, env: Any, step: int, among: np.ndarray | None = None, now: np.ndarray | None = None
    ) -> np.ndarray:
        """Unit guide directions (N, 3) at control step ``step`` (counted from the reset; any subset of steps).

        ``among`` (N,) bool: plan only these flights when due (the others' images are still mapped); default all.
        ``now`` (N,) bool: flights planned at this call whether due or not.
        """
        pos, goal = env.local_pos, env.goal_buf
        due = self.map.due(env, step)
        todo = due if among is None else due[among[due]]
        if now is not None:
            todo = np.union1d(todo, np.flatnonzero(now))
        if self.delay == 0:
            for i in todo:
                self.target[i] = self.map.plan(int(i), pos[i], goal[i])
        else:  # this step's map and position, flown from step + delay: the same plans, inline or on the pool
            m = self.map
            for i in todo:
                job = (m.grid[i].copy(), None if m.seen is None else m.seen[i].copy(), pos[i].copy(), goal[i].copy())
                res = self.pool.submit(m.plan_on, *job) if self.pool is not None else m.plan_on(*job)
                self._pending.append((step + self.delay, int(i), res))
            while self._pending and self._pending[0][0] <= step:  # in the order planned: a newer plan wins
                _, i, res = self._pending.pop(0)
                self.target[i] = res.result() if isinstance(res, Future) else res
        guide = _unit(goal - pos)
        aim = np.isfinite(self.target[:, 0])  # NaN: the plan reaches the goal region, fly at the goal
        if aim.any():
            d = np.concatenate((self.target[aim] - pos[aim, :2], (goal - pos)[aim, 2:3]), axis=1)
            guide[aim] = _unit(d)
        return guide


class Controller:
    """Interface: ``reset(env)`` at the start of a batch of trials, ``commands(env)`` each control step."""

    privileged: bool = False
    """Whether the controller reads privileged map information (the table labels such rows)."""
    reads_depth: bool = True
    """Whether the controller reads the depth image; if not (and no shield is in the loop) the harness skips the
    ray casting for its row."""

    def reset(self, env: Any) -> None:
        """Start a new batch of trials in ``env``."""

    def commands(self, env: Any, among: np.ndarray | None = None) -> np.ndarray:
        """Commands (N, 4) = [f_n, phi, theta, psi] for every env (frozen envs are ignored by the env).

        ``among`` (N,) bool: the flights whose commands the caller flies (a stall handover's); a planner may plan only
        those (the reactive planners do), the others command every flight each step. Default all.
        """
        raise NotImplementedError


class GoalSeeker(Controller):
    """Straight to the goal at the target speed: v_des = v_target (g - p) / |g - p|, yaw towards the goal."""

    reads_depth = False

    def __init__(self, cfg: BaselineConfig) -> None:  # noqa: D107
        self.cfg = cfg

    def commands(self, env: Any, among: np.ndarray | None = None) -> np.ndarray:  # noqa: D102
        pos, vel = env.local_pos, env.vehicles.vel_w
        to_goal = env.goal_buf - pos
        v_des = _unit(to_goal) * env.target_speed_buf[:, None]
        a = self.cfg.tracking.k_v * (v_des - vel)
        psi = np.arctan2(to_goal[:, 1], to_goal[:, 0])
        return accel_to_command(a, psi, self.cfg.tracking, env.cfg.vehicle.gravity)


class OracleController(Controller):
    """Privileged: descend the geodesic field Phi (distance to the goal region around obstacles).

    v_des = s * v_target * (-grad Phi / |grad Phi|) at the look-ahead point q = p + v * lookahead, plus the
    repulsion k (d_rep - d(p)) grad d(p) where the ESDF d(p) < d_rep; the speed scale
    s = clip(d(q) / slow_dist, s_min, 1) slows down where the look-ahead point is tight. grad Phi is a central
    difference with step h: (Phi(q + h e_i) - Phi(q - h e_i)) / 2h. Within ``goal_switch`` of the goal region
    (Phi(p) small) the direction becomes (g - p) / |g - p|: Phi is 0 on the whole goal box, the goal is a point.

    With ``guidance: euclidean`` the direction is (g - q) / |g - q| instead (the descent of the Euclidean distance
    to the goal point g), everything else unchanged: the same controller with the Distance reward's potential,
    which has local minima behind non-convex obstacles (U-traps, dead ends) where the geodesic field has none.
    """

    privileged = True
    reads_depth = False

    def __init__(self, cfg: BaselineConfig) -> None:  # noqa: D107
        self.cfg = cfg

    def _fields(self, env: Any) -> tuple[Any, Any]:
        """(region FieldStack, GoalAnchorFields or None) to descend: the env's, or the oracle's inflated ones."""
        radius = self.cfg.oracle.field_radius
        if radius <= 0:
            return env.field_stack, getattr(env, "anchor_fields", None)
        own = getattr(self, "_own", None)
        if own is None or own[0] is not env:
            from envs.fields import scene_field_stack
            from envs.fields.anchors import GoalAnchorFields

            stack = scene_field_stack(env.scenes, env.cfg.scenes.field_resolution, radius)  # lazy, like the env's
            anchors = env.anchor_fields
            k = anchors.count if anchors is not None else 0
            own = (env, stack, GoalAnchorFields(env.scenes, stack, k, lazy=True) if k > 0 else None)
            self._own = own
        return own[1], own[2]

    def _geodesic(self, env: Any, ids: np.ndarray, pts: np.ndarray, per_env: int) -> np.ndarray:
        """Phi at ``per_env`` consecutive points per env: the episode goal's anchor field or the region field."""
        stack, anchor_fields = self._fields(env)
        if self.cfg.oracle.episode_goal and anchor_fields is not None:
            anchors = np.repeat(env.anchor_buf, per_env)
            return anchor_fields.geodesic(np.repeat(ids, per_env), anchors, pts)
        return stack.geodesic(np.repeat(ids, per_env), pts)

    def _descent(self, env: Any, ids: np.ndarray, q: np.ndarray) -> np.ndarray:
        """-grad Phi / |grad Phi| at the points q (N, 3), by central differences of step ``fd_step``."""
        h = self.cfg.oracle.fd_step
        offsets = np.concatenate((np.eye(3) * h, -np.eye(3) * h))  # (6, 3)
        pts = (q[:, None, :] + offsets[None]).reshape(-1, 3)
        phi = self._geodesic(env, ids, pts, 6).reshape(len(q), 6)
        # Points just past the goal region (x beyond the scene) read Phi(clamped) + outside: still descend to goal.
        return -_unit((phi[:, :3] - phi[:, 3:]) / (2 * h))

    def guide(self, env: Any, q: np.ndarray) -> np.ndarray:
        """Unit descent direction (N, 3) of the guidance potential, read at the points q (one per env).

        Within ``goal_switch`` of the goal (by that potential, measured at the vehicle): straight at the goal point.
        """
        oc = self.cfg.oracle
        pos, ids = env.local_pos, env.scene_id_buf
        if oc.guidance == "euclidean":
            # -grad |g - q| = (g - q) / |g - q|: straight at the goal, blind to the obstacles between.
            direction = _unit(env.goal_buf - q)
            near = np.linalg.norm(env.goal_buf - pos, axis=1) < oc.goal_switch
        else:
            direction = self._descent(env, ids, q)
            near = self._geodesic(env, ids, pos, 1) < oc.goal_switch
        direction[near] = _unit(env.goal_buf[near] - pos[near])
        return direction

    def commands(self, env: Any, among: np.ndarray | None = None) -> np.ndarray:  # noqa: D102
        oc = self.cfg.oracle
        pos, vel = env.local_pos, env.vehicles.vel_w
        ids = env.scene_id_buf
        q = pos + vel * oc.lookahead_s
        d_now, g_now, _ = env.field_stack.query(ids, pos, geodesic=False)
        d_ahead = env.field_stack.esdf(ids, q)
        scale = np.clip(d_ahead / oc.slow_dist, oc.min_speed_fraction, 1.0)
        direction = self.guide(env, q)
        v_des = direction * (scale * env.target_speed_buf)[:, None]
        deficit = np.maximum(oc.repulse_dist - d_now, 0.0)
        v_des += oc.repulse_gain * deficit[:, None] * _unit(g_now)
        a = self.cfg.tracking.k_v * (v_des - vel)
        psi = np.arctan2(v_des[:, 1], v_des[:, 0])
        return accel_to_command(a, psi, self.cfg.tracking, env.cfg.vehicle.gravity)


def free_distances(points: np.ndarray, origin: np.ndarray, dirs: np.ndarray, radius: float, cap: float) -> np.ndarray:
    """Free distance along each unit direction before a point comes within ``radius`` of the ray.

    For a point at r = o_pt - origin, the along-ray distance is s = r.d and the squared distance to the ray's line
    is e^2 = |r|^2 - s^2. The ray p(t) = origin + t d first comes within ``radius`` of the point at
    t = s - sqrt(radius^2 - e^2) (if e < radius and that t is ahead). A point already within ``radius`` of the
    origin and ahead (s > 0) blocks at t = 0. Returns (K,) distances, capped at ``cap``.
    """
    if len(points) == 0:
        return np.full(len(dirs), cap)
    r = points - origin  # (M, 3)
    s = r @ dirs.T  # (M, K)
    e2 = np.einsum("ij,ij->i", r, r)[:, None] - s * s
    hit = (e2 < radius * radius) & (s > 0)
    t = s - np.sqrt(np.maximum(radius * radius - e2, 0.0))
    t = np.where(hit, np.maximum(t, 0.0), cap)
    return np.minimum(t.min(axis=0), cap)


class ReactivePlanner(Controller):
    """Depth-only motion-primitive planner (see the module docstring); no map, no memory beyond one frame.

    Each replan: points P from the sensor depth image; K primitive directions d_k (heading-relative azimuth and
    elevation); free distance f_k (:func:`free_distances`); score
    ``w_goal cos(d_k, goal) + w_free min(f_k, H) / H - w_smooth |d_k - d_prev|`` over primitives with
    f_k >= min_free. The speed along the best one obeys v = min(v_target, sqrt(2 a_brake max(f - margin, 0))), so
    the vehicle can always stop short of what it sees. With no free primitive it brakes (v_des = 0) and turns its
    heading towards the goal side to look for a gap. Yaw follows the chosen direction, so the camera looks where
    the vehicle flies.
    """

    def __init__(self, cfg: BaselineConfig) -> None:  # noqa: D107
        self.cfg = cfg
        rc = cfg.reactive
        az, el = np.meshgrid(np.radians(rc.azimuths_deg), np.radians(rc.elevations_deg), indexing="ij")
        self._az = az.reshape(-1)
        self._el = el.reshape(-1)
        self._v_des: np.ndarray | None = None
        self._psi: np.ndarray | None = None
        self._step = 0
        self._oracle = OracleController(replace(cfg, oracle=replace(cfg.oracle, guidance="geodesic")))
        self.privileged = rc.guidance == "geodesic"
        self.plan_pool: Executor | None = None
        """With ``guidance: map`` and ``camera_map.plan_delay_steps`` >= 1: where the map's plans run (set before
        :meth:`reset`; the deploy loop's planning thread); None: inline."""

    def reset(self, env: Any) -> None:  # noqa: D102
        n = env.num_envs
        self._v_des = np.zeros((n, 3))
        self._psi = _heading(env.vehicles.R_wb).copy()
        self._dir = np.zeros((n, 3))
        self._planned = np.zeros(n, dtype=bool)  # flights planned at least once since the reset
        self._step = 0
        self._map = (
            MapGuide(self.cfg.reactive.camera_map, env, self.plan_pool) if self.cfg.reactive.guidance == "map" else None
        )

    def _plan(self, env: Any, i: int, guide: np.ndarray) -> None:
        rc = self.cfg.reactive
        pos = env.local_pos[i]
        r_wb = env.vehicles.R_wb[i]
        psi0 = math.atan2(r_wb[1, 0], r_wb[0, 0])
        pts = depth_to_points(env.sensor_depth_buf[i], pos, r_wb, env.cfg.camera, rc.voxel or None)
        a = psi0 + self._az
        dirs = np.stack((np.cos(a) * np.cos(self._el), np.sin(a) * np.cos(self._el), np.sin(self._el)), axis=1)
        free = free_distances(pts, pos, dirs, rc.collision_radius, rc.horizon)
        to_goal = guide[i]
        score = rc.w_goal * (dirs @ to_goal) + rc.w_free * free / rc.horizon
        score -= rc.w_smooth * np.linalg.norm(dirs - self._dir[i], axis=1)
        # Keep inside the flight volume: no climbing within 0.4 m of the ceiling, no descending near the floor.
        lo, hi = env.scenes[env.scene_id_buf[i]].bounds_lo, env.scenes[env.scene_id_buf[i]].bounds_hi
        score[(dirs[:, 2] > 0) & (pos[2] > hi[2] - 0.6)] = -np.inf
        score[(dirs[:, 2] < 0) & (pos[2] < lo[2] + 0.6)] = -np.inf
        score[free < rc.min_free] = -np.inf
        k = int(np.argmax(score))
        if not np.isfinite(score[k]):
            # Nothing free: brake, and turn towards the goal's side to look for a gap.
            side = math.copysign(1.0, math.sin(math.atan2(to_goal[1], to_goal[0]) - psi0) or 1.0)
            self._v_des[i] = 0.0
            self._psi[i] = psi0 + side * math.radians(rc.search_turn_deg)
            self._dir[i] = 0.0
            return
        v = min(float(env.target_speed_buf[i]), math.sqrt(2 * rc.brake_accel * max(free[k] - rc.stop_margin, 0.0)))
        self._v_des[i] = dirs[k] * v
        self._psi[i] = a[k]
        self._dir[i] = dirs[k]

    def commands(self, env: Any, among: np.ndarray | None = None) -> np.ndarray:
        """Commands (N, 4) for every env.

        ``among`` (N,) bool: plan only these flights (the others' commands are stale; their images still enter a
        ``map`` guide), and a flight new to ``among`` plans at once. Default all.
        """
        if self._v_des is None:
            self.reset(env)
        live = ~env.frozen_buf if among is None else ~env.frozen_buf & among
        fresh = live & ~self._planned
        every = self._step % self.cfg.reactive.replan_every == 0
        if every or fresh.any():
            if self.cfg.reactive.guidance == "geodesic":
                guide = self._oracle.guide(env, env.local_pos)
            elif self._map is not None:
                guide = self._map(env, self._step, among, fresh)
            else:
                guide = _unit(env.goal_buf - env.local_pos)
            for i in np.flatnonzero(live if every else fresh):
                self._plan(env, int(i), guide)
            self._planned |= live if every else fresh
        self._step += 1
        a = self.cfg.tracking.k_v * (self._v_des - env.vehicles.vel_w)
        return accel_to_command(a, self._psi, self.cfg.tracking, env.cfg.vehicle.gravity)


class GeodesicReactivePlanner(ReactivePlanner):
    """The reactive planner aligned with -grad Phi instead of the goal direction (the ``reactive_geodesic`` row).

    Privileged global guidance on top of the same depth-only local avoidance.
    """

    privileged = True

    def __init__(self, cfg: BaselineConfig) -> None:  # noqa: D107
        super().__init__(replace(cfg, reactive=replace(cfg.reactive, guidance="geodesic")))


class MapReactivePlanner(ReactivePlanner):
    """The reactive planner guided by a plan over the map its own camera has shown (the ``reactive_map`` row).

    Not privileged: ``reactive.guidance: map`` (:class:`ReactiveConfig`). Same local avoidance as ``reactive``.
    """

    def __init__(self, cfg: BaselineConfig) -> None:  # noqa: D107
        super().__init__(replace(cfg, reactive=replace(cfg.reactive, guidance="map")))


class EuclideanOracleController(OracleController):
    """The oracle with ``guidance: euclidean`` whatever the config says (the ``oracle_euclidean`` row)."""

    def __init__(self, cfg: BaselineConfig) -> None:  # noqa: D107
        super().__init__(replace(cfg, oracle=replace(cfg.oracle, guidance="euclidean")))


class OracleExpert:
    """The oracle as a DAgger expert: its command for every env's current state, as a normalised action.

    ``expert(env)`` returns (N, 4) actions in [-1, 1] (``env.command_to_action`` of the oracle's command, clipped
    where the command exceeds the action range, e.g. a yaw lead beyond ``action.yaw_range_deg``). The oracle is
    stateless, so the label depends only on the state the *student* reached: DAgger labels (Ross et al. 2011) with
    a privileged expert, as in Loquercio et al. 2021 (Science Robotics, "Learning high-speed flight in the wild").
    """

    def __init__(self, cfg: BaselineConfig | None = None) -> None:  # noqa: D107
        self.controller = OracleController(cfg or BaselineConfig(oracle=OracleConfig(episode_goal=True)))

    def __call__(self, env: Any) -> np.ndarray:
        """Expert actions (N, 4) for the env's current state."""
        act = np.clip(env.command_to_action(self.controller.commands(env)), -1.0, 1.0)
        if not np.isfinite(act).all():
            bad = np.flatnonzero(~np.isfinite(act).all(axis=1)).tolist()
            raise FloatingPointError(f"oracle expert produced non-finite actions for env(s) {bad}")
        return act


class PlannerExpert(OracleExpert):
    """The planning expert (:class:`shield_nav.algorithms.expert.PlannerController`) as a DAgger expert.

    Its route hysteresis (``expert.commit_dist``) remembers each env's last path: it is asked once per env step (the
    adapter does), and an env whose episode restarts gets a fresh path, so the label still follows the state the
    student reached.
    """

    def __init__(self, cfg: BaselineConfig | None = None) -> None:  # noqa: D107
        self.controller = PlannerController(cfg or BaselineConfig())


class CameraMapExpert(OracleExpert):
    """The camera-routed planning expert (:class:`~shield_nav.algorithms.expert_cammap.CameraMapPlanner`), for DAgger.

    Its route comes from the map of what each env's own camera has shown, so its labels turn where the images (and
    their memory) explain a turn, not where only the scene's map would. In training, envs restart on their own: an
    env whose episode restarts (``episode_length_buf`` 0 at the call) gets an empty map, its first image mapped at
    once, and a plan in the same call. Its local geometry (the ESDF the tracker and speed profile read) is the
    scene's, as in the ``expert_cammap`` row. The env must render depth (a distillation student reads it anyway).
    """

    def __init__(self, cfg: BaselineConfig | None = None) -> None:  # noqa: D107
        self.controller = CameraMapPlanner(cfg or BaselineConfig())

    def __call__(self, env: Any) -> np.ndarray:
        """Expert actions (N, 4) for the env's current state; restarted envs first forget their map."""
        ctl = self.controller
        if getattr(ctl, "_env", None) is not env:
            ctl.reset(env)
        fresh = np.flatnonzero(np.asarray(env.episode_length_buf) == 0)
        if fresh.size:
            ctl.restart(env, fresh)
        return super().__call__(env)


EXPERTS = {"oracle": OracleExpert, "planner": PlannerExpert, "planner_cammap": CameraMapExpert}
"""Scripted experts a distillation run can imitate (``runner.expert.kind``)."""


BASELINES = {
    "oracle": OracleController,
    "oracle_euclidean": EuclideanOracleController,
    "reactive": ReactivePlanner,
    "reactive_geodesic": GeodesicReactivePlanner,
    "reactive_map": MapReactivePlanner,
    "goal": GoalSeeker,
    "expert": PlannerController,
    "expert_cammap": CameraMapPlanner,
}
"""Baseline controllers by the ``controller`` name a row uses."""


def make_baseline(kind: str, cfg: BaselineConfig) -> Controller:
    """The baseline controller ``kind`` (one of :data:`BASELINES`)."""
    if kind not in BASELINES:
        raise ValueError(f"unknown baseline controller {kind!r}; known: {sorted(BASELINES)}")
    return BASELINES[kind](cfg)
