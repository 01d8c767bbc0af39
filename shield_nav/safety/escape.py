"""A stall escape for a deployed depth policy: when a flight stops closing on its goal, point the goal input sideways.

A goal-seeking depth policy that meets a pocket open away from the goal (a dead end of a Perlin field, a box maze's
closed corridor) can circle or hover in it until its time limit: its image shows no way on, and its goal input keeps
pulling it back to the pocket's far wall. :class:`StallEscape` is a layer between the goal and the policy that uses
nothing the policy does not already read (its own position and heading estimate, the goal, the depth image):

- **Stalled**: the straight-line distance to the goal has not gone ``min_progress`` below its best within the last
  ``window_s`` seconds.
- **Escape**: for ``hold_s`` seconds the policy's goal input (``goal_xy_h`` of :data:`envs.navigation.env.STATE_LAYOUT`)
  points along a horizontal direction at 90 deg to the goal's, as if the goal lay ``goal_distance`` or more that way;
  the goal's height input stays. The first side of a flight is the one whose half of the depth image shows more free
  range (each column's mean of ``min(depth, depth_cap)``); each later escape of the flight takes the other side and
  holds ``hold_growth_s`` longer.
- After the hold the true goal input returns, and the best distance starts afresh from the current one.
- **Circling** (``circle_turns`` > 0, off by default): a flight also counts as stalled when its heading, read from
  the state's attitude, has turned ``circle_turns`` full turns or more, net, over the last ``circle_window_s``
  seconds (or since its start, if younger): a flight orbiting a pocket, which the distance rule sees only after
  ``window_s`` without progress. Its heading history restarts when its escape starts.

With ``kind: map`` the response to a stall is a plan instead: every flight maps what its camera shows (a 2D
occupancy grid over the flight volume, the image's points near the vehicle's height), and from its first stall on,
every ``replan_s`` a Dijkstra from the goal over that map (mapped cells inflated by ``map_inflate``, unknown cells
free: the optimistic planning of classical explorers) gives the way; the goal input points at the way's cell about
``lookahead`` metres on (steepest descent), until the goal is within ``2 goal_radius``.

The shield, the success test and the time limit are untouched: the layer only changes which way the policy is asked
to fly, and only in flights that are not closing on their goal. Vectorised over the batch; no per-env Python loop.
Its measured effect is in docs/shield.md ("Stall escape") and the lab log (2026-12-03, session 77).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from envs.camera.config import CameraConfig
from envs.config import require
from envs.navigation.env import STATE_LAYOUT
from shield_nav.safety.camera_map import (
    CameraMap,
)


def _slice(name: str) -> slice:
    """The columns of ``name`` in the policy's state vector."""
    start = 0
    for key, size, _ in STATE_LAYOUT:
        if key == name:
            return slice(start, start + size)
        start += size
    raise KeyError(name)


GOAL_COLUMNS = _slice("goal_xy_h")
"""Columns of the heading-frame goal vector in the state (two)."""
ROT_COLUMNS = _slice("R_wb")
"""Columns of the body-to-world rotation (row-major) in the state (nine)."""
ESCAPE_KINDS = ("sideways", "map", "handover")
"""Values of :attr:`EscapeConfig.kind`."""


@dataclass
class EscapeConfig:
    """Stall-escape parameters (rows with ``escape: true``; lengths m, times s)."""

    window_s: float = 5.0
    """A flight is stalled when its distance to the goal has not gone ``min_progress`` below its best for this long."""
    min_progress: float = 1.0
    """Progress [m] that counts as closing on the goal."""
    hold_s: float = 4.0
    """Duration of a flight's first escape."""
    hold_growth_s: float = 2.0
    """Each later escape of the same flight holds this much longer than the one before."""
    goal_distance: float = 10.0
    """The escape's virtual goal lies at least this far along the escape direction (the goal input's saturation:
    the state scales the goal vector by ``max(|offset|, 10 m)``)."""
    depth_cap: float = 10.0
    """Depth [m] beyond which the image counts as free when choosing the first side."""
    bounds_margin: float = 0.0
    """0: off. If > 0 (with the flight volume's horizontal bounds given, the operator's geofence, not the obstacles),
    a side whose direction reaches the bounds within this distance [m] of the vehicle is not taken while the other
    side has the room (both short: the side with more room), and a hold ends early when the room left ahead along
    its direction falls below ``bounds_stop``."""
    bounds_stop: float = 2.0
    """With ``bounds_margin`` > 0: the room [m] ahead to the bounds at which a hold ends early."""
    circle_turns: float = 0.0
    """0: off. If > 0, a flight whose heading turned this many full turns, net, over the last ``circle_window_s``
    also counts as stalled (either kind; see the module docstring)."""
    circle_window_s: float = 6.0
    """With ``circle_turns`` > 0: the window [s] of the net heading rotation."""
    kind: str = "sideways"
    """``sideways``: the escape above. ``map``: from its first stall on, a flight follows a planner over the map of
    what its camera has seen (see :class:`StallEscape`; needs the flight volume's bounds, the camera and R_wb).
    ``handover``: from its first stall on, a flight is flown by the ``handover_planner`` instead of the policy (the
    evaluation harness swaps the commands; :attr:`StallEscape.guided` says which flights)."""
    handover_planner: str = "reactive_map"
    """``handover``: the baseline controller (a row's ``controller`` name,
    :data:`shield_nav.algorithms.baselines.BASELINES`) that flies a stalled flight. ``reactive_map`` (default): the
    weight-free camera-map planner, what a vehicle can fly; the privileged ones (``expert``, ``expert_cammap``) measure
    what a better flyer could do from the stall on (``eval.py`` only; the deploy loop refuses them)."""
    map_cell: float = 0.2
    """``map``: the occupancy grid's cell [m] (2D, over the flight volume's horizontal bounds)."""
    map_range: float = 12.0
    """``map``: image points farther than this [m] from the vehicle are not mapped."""
    map_band: float = 0.6
    """``map``: only points within this height [m] of the vehicle are mapped (and none below ``map_floor``)."""
    map_floor: float = 0.3
    """``map``: points lower than this [m] above the volume's floor are ground, not obstacles."""
    map_inflate: float = 0.3
    """``map``: mapped cells block the plan within this distance [m] (the vehicle's radius and a margin)."""
    map_every: int = 5
    """``map``: control steps between map updates."""
    replan_s: float = 0.25
    """``map``: seconds between plans of a guided flight."""
    lookahead: float = 5.0
    """``map``: the guided goal input points at the plan's path this far [m] from the vehicle."""
    goal_radius: float = 5.0
    """``map``: the plan's goal region, and within this distance of the goal the true goal input returns (the
    env's ``episode.goal_radius``)."""
    plan_delay_steps: int = 0
    """``map`` (the camera-map planner's guide, :class:`shield_nav.algorithms.baselines.MapGuide`): control steps
    between a plan's inputs (this step's map and position) and the step that first flies it. 0 (default): the same step,
    the plan computed inline. ``L`` >= 1: the plan is flown from step ``k + L``, so on a vehicle it can be computed on a
    thread of its own while the control steps go on (``ShieldedPilot(..., replan_delay=L)``); ``eval.py`` flies the
    same delay inline, so both fly the same flight. Read by the planner's map (``baselines.reactive.camera_map``);
    the stall escape's own section refuses it."""
    map_unknown_cost: float = 1.0
    """``map``: what a metre through space the camera has not shown costs the plan, against 1 through space it has
    shown free. 1 (default): unseen space is free space, the optimistic plan. Above 1 the map also keeps which
    cells each image showed (:meth:`CameraMap.observe`) and the plan prefers the ways the camera has seen."""

    def validate(self, prefix: str = "") -> None:
        """Reject bad values, naming the key."""
        require(self.kind in ESCAPE_KINDS, f"{prefix}kind", f"must be one of {list(ESCAPE_KINDS)}, got {self.kind!r}")
        from shield_nav.algorithms.baselines import BASELINES  # the baselines import this module

        require(self.handover_planner in BASELINES, f"{prefix}handover_planner",
                f"must be one of {sorted(BASELINES)}, got {self.handover_planner!r}")  # fmt: skip
        require(self.map_every >= 1, f"{prefix}map_every", f"must be >= 1, got {self.map_every}")
        for key in ("window_s", "min_progress", "hold_s", "goal_distance", "depth_cap", "bounds_stop", "map_cell",
                    "map_range", "map_band", "map_inflate", "replan_s", "lookahead", "goal_radius",
                    "circle_window_s"):  # fmt: skip
            v = getattr(self, key)
            require(math.isfinite(v) and v > 0, f"{prefix}{key}", f"must be finite and > 0, got {v}")
        for key in ("hold_growth_s", "bounds_margin", "map_floor", "circle_turns"):
            v = getattr(self, key)
            require(math.isfinite(v) and v >= 0, f"{prefix}{key}", f"must be finite and >= 0, got {v}")
        require(self.plan_delay_steps >= 0, f"{prefix}plan_delay_steps", f"must be >= 0, got {self.plan_delay_steps}")
        v = self.map_unknown_cost
        require(math.isfinite(v) and v >= 1.0, f"{prefix}map_unknown_cost", f"must be finite and >= 1, got {v}")


class StallEscape:
    """Per-flight stall detector and goal-input override for a batch of ``n`` flights (see the module docstring).

    Call :meth:`apply` once per control step, before the policy reads the observation; it returns the state the
    policy should read (a copy when any flight escapes). ``t`` counts control steps of ``dt`` seconds from the reset.
    """

    def __init__(self, cfg: EscapeConfig, n: int, dt: float, camera: CameraConfig | None = None) -> None:  # noqa: D107
        cfg.validate("escape.")
        if cfg.kind == "map" and camera is None:
            raise ValueError("stall escape: escape.kind 'map' needs the camera configuration")
        if cfg.plan_delay_steps:
            raise ValueError(
                f"stall escape: escape.plan_delay_steps {cfg.plan_delay_steps}; the escape plans inline, the delay is "
                "the handover planner's (baselines.reactive.camera_map.plan_delay_steps)"
            )
        self.cfg, self.n, self.dt, self.camera = cfg, n, dt, camera
        self.map: CameraMap | None = None  # kind 'map': what each flight's camera has shown (made at the first call)
        self.guided = np.zeros(n, dtype=bool)
        self.next_plan = np.zeros(n)
        self.target = np.full((n, 2), np.nan)
        self.best = np.full(n, np.inf)
        self.best_t = np.zeros(n)
        self.until = np.full(n, -np.inf)
        self.direction = np.zeros((n, 2))
        self.count = np.zeros(n, dtype=np.int64)
        self.side = np.zeros(n)
        self.escape_steps = np.zeros(n, dtype=np.int64)
        self.circled = np.zeros(n, dtype=np.int64)  # escapes started by the circling rule
        k = max(int(round(cfg.circle_window_s / dt)), 1)
        self.turned = np.zeros(n)  # unwrapped heading change since the reset [rad]
        self.turned_hist = np.zeros((k, n))  # ring buffer of ``turned`` over the last k steps
        self.turned_from = np.zeros(n)  # ``turned`` at a flight's start or its latest escape
        self.escape_t = np.full(n, -1, dtype=np.int64)  # step of a flight's latest escape start (-1: none)
        self.psi_prev: np.ndarray | None = None
        self.last_t = -1

    def apply(
        self,
        state: np.ndarray,
        pos: np.ndarray,
        goal: np.ndarray,
        depth_m: np.ndarray,
        t: int,
        live: np.ndarray | None = None,
        bounds: tuple[np.ndarray, np.ndarray] | None = None,
        R_wb: np.ndarray | None = None,  # noqa: N803
        floor: float = 0.0,
    ) -> np.ndarray:
        """The policy's state (N, S) with the goal input of escaping flights replaced.

        ``pos``, ``goal`` (N, 3): the vehicle's position estimate and its goal (the quantities the state's goal
        vector is computed from); ``depth_m`` (N, 1, H, W) metric depth (0 or non-finite: no return, counted free);
        ``live`` (N,) bool: flights still flying (default all); a finished flight starts no escape and counts no
        escape step. ``bounds``: the flight volume's horizontal corners ``(lo, hi)``, each (2,) or (N, 2), in the
        frame of ``pos`` (read with ``bounds_margin`` > 0 or ``kind: map``, which then require them). ``R_wb``
        (N, 3, 3) the body attitude of the image and ``floor`` the volume's floor height (``kind: map``).
        """
        cfg, now = self.cfg, t * self.dt
        if not np.isfinite(state).all() or not np.isfinite(pos).all():
            raise FloatingPointError("stall escape: non-finite state or position")
        live = np.ones(self.n, dtype=bool) if live is None else np.asarray(live, dtype=bool)
        dist = np.linalg.norm(goal - pos, axis=1)
        gained = dist < self.best - cfg.min_progress  # the stall clock of both kinds
        self.best = np.where(gained, dist, self.best)
        self.best_t = np.where(gained, now, self.best_t)
        circling = self._circling(state, t)
        if cfg.kind == "map":
            return self._apply_map(state, pos, goal, depth_m, t, live, bounds, R_wb, floor, dist, circling)
        if cfg.kind == "handover":  # only the stall rules: the harness hands the guided flights to a planner
            self._guide_stalled(live, circling, t)
            self.escape_steps += self.guided & live
            return state
        if cfg.bounds_margin > 0 and bounds is None:
            raise ValueError("stall escape: escape.bounds_margin > 0 needs the flight volume's bounds")
        use_bounds = bounds if cfg.bounds_margin > 0 else None
        to_goal = goal[:, :2] - pos[:, :2]
        escaping = now < self.until
        if use_bounds is not None and escaping.any():  # a hold ends where the volume's side comes near
            room = _room(pos[:, :2], self.direction, *use_bounds)
            stop = escaping & (room < cfg.bounds_stop)
            self.until[stop] = now
            escaping &= ~stop
        ended = ~escaping & (self.best_t < self.until)  # a hold is over: a fresh window from the current distance
        self.best = np.where(ended, dist, self.best)
        self.best_t = np.where(ended, now, self.best_t)
        stalled = live & ~escaping & ((now - self.best_t >= cfg.window_s) | circling)
        if stalled.any():
            self._count_circling(stalled, circling & (now - self.best_t < cfg.window_s), t)
            self._start(np.flatnonzero(stalled), to_goal, state, depth_m, now, pos, use_bounds)
            escaping = now < self.until
        if not escaping.any():
            return state
        self.escape_steps += escaping & live
        i = np.flatnonzero(escaping)
        return _with_goal_direction(state, i, self.direction[i])

    def _apply_map(
        self,
        state: np.ndarray,
        pos: np.ndarray,
        goal: np.ndarray,
        depth_m: np.ndarray,
        t: int,
        live: np.ndarray,
        bounds: tuple[np.ndarray, np.ndarray] | None,
        R_wb: np.ndarray | None,  # noqa: N803
        floor: float,
        dist: np.ndarray,
        circling: np.ndarray,
    ) -> np.ndarray:
        """``kind: map``: map the image, detect stalls, and steer guided flights along their plan."""
        cfg, now = self.cfg, t * self.dt
        if bounds is None or R_wb is None:
            raise ValueError("stall escape: escape.kind 'map' needs the flight volume's bounds and R_wb")
        if self.map is None:
            self.map = CameraMap(cfg, self.n, self.camera, *bounds)  # type: ignore[arg-type]
        if t % cfg.map_every == 0:
            self.map.observe(np.flatnonzero(live), pos, R_wb, depth_m, floor)
        self._guide_stalled(live, circling, t)
        due = np.flatnonzero(self.guided & live & (now >= self.next_plan))
        for i in due:
            self.target[i] = self.map.plan(i, pos[i], goal[i])
            self.next_plan[i] = now + cfg.replan_s
        steer = self.guided & live & np.isfinite(self.target[:, 0]) & (dist > 2.0 * cfg.goal_radius)
        if not steer.any():
            return state
        self.escape_steps += steer
        i = np.flatnonzero(steer)
        e = self.target[i] - pos[i, :2]
        return _with_goal_direction(state, i, e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-9))

    def _guide_stalled(self, live: np.ndarray, circling: np.ndarray, t: int) -> None:
        """``map`` and ``handover``: live flights not yet guided that stall now (either rule) are guided from now on."""
        waited = t * self.dt - self.best_t >= self.cfg.window_s
        stalled = live & ~self.guided & (waited | circling)
        self._count_circling(stalled, circling & ~waited, t)
        self.guided |= stalled
        self.count[stalled] = 1

    def _circling(self, state: np.ndarray, t: int) -> np.ndarray:
        """(N,) bool: flights whose heading turned ``circle_turns`` or more, net, over the last ``circle_window_s``.

        All False with ``circle_turns`` 0. The heading history needs one call per control step: a skipped or
        repeated ``t`` raises.
        """
        cfg = self.cfg
        if cfg.circle_turns <= 0:
            return np.zeros(self.n, dtype=bool)
        if t != self.last_t + 1:
            raise ValueError(f"stall escape: the circling rule needs one call per control step, got t = {t} after "
                             f"{self.last_t}")  # fmt: skip
        self.last_t = t
        psi = _heading(state)
        if self.psi_prev is not None:
            self.turned += (psi - self.psi_prev + np.pi) % (2.0 * np.pi) - np.pi
        self.psi_prev = psi
        k = self.turned_hist.shape[0]
        # The turn k steps ago, unless the flight started or escaped since.
        recent = (self.escape_t > t - k) | (t < k)
        ago = np.where(recent, self.turned_from, self.turned_hist[t % k])
        self.turned_hist[t % k] = self.turned
        return np.abs(self.turned - ago) >= 2.0 * np.pi * cfg.circle_turns

    def _count_circling(self, started: np.ndarray, by_circling: np.ndarray, t: int) -> None:
        """Book escapes ``started`` (N,) bool, ``by_circling`` those the distance rule alone would not have started."""
        self.circled += started & by_circling
        self.turned_from = np.where(started, self.turned, self.turned_from)
        self.escape_t = np.where(started, t, self.escape_t)

    def _start(
        self,
        ids: np.ndarray,
        to_goal: np.ndarray,
        state: np.ndarray,
        depth_m: np.ndarray,
        now: float,
        pos: np.ndarray,
        bounds: tuple[np.ndarray, np.ndarray] | None,
    ) -> None:
        """Begin an escape for flights ``ids``: choose the side, fix the direction, set the hold."""
        cfg = self.cfg
        g = to_goal[ids]
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        u = np.where(norm > 1e-9, g / np.maximum(norm, 1e-9), np.array([1.0, 0.0]))
        left = np.stack((-u[:, 1], u[:, 0]), axis=1)  # the goal direction turned +90 deg (z up)
        first = self.count[ids] == 0
        side = -self.side[ids]  # later escapes: the other side
        if first.any():
            f = ids[first]
            d = np.asarray(depth_m[f, 0], dtype=np.float64)
            free = np.where(np.isfinite(d) & (d > 0), np.minimum(d, cfg.depth_cap), cfg.depth_cap)
            w = free.shape[-1]
            img_left = free[:, :, : w // 2].mean(axis=(1, 2))  # image left = body +y (envs/camera/model.py)
            img_right = free[:, :, w - w // 2 :].mean(axis=(1, 2))
            psi = _heading(state[f])
            lat = -np.sin(psi) * left[first, 0] + np.cos(psi) * left[first, 1]  # +90 deg's heading-frame y
            free_plus = np.where(lat >= 0, img_left, img_right)  # the image half the +90 deg side lies in
            free_minus = np.where(lat >= 0, img_right, img_left)
            side[first] = np.where(free_plus >= free_minus, 1.0, -1.0)
        if bounds is not None:  # a side that runs into the volume's side within bounds_margin gives way
            lo, hi = (np.broadcast_to(np.asarray(b, dtype=np.float64), (self.n, 2))[ids] for b in bounds)
            room_plus = _room(pos[ids, :2], left, lo, hi)
            room_minus = _room(pos[ids, :2], -left, lo, hi)
            ok_plus, ok_minus = room_plus >= cfg.bounds_margin, room_minus >= cfg.bounds_margin
            side = np.where(ok_plus & ~ok_minus, 1.0, np.where(ok_minus & ~ok_plus, -1.0, side))
            neither = ~ok_plus & ~ok_minus
            side[neither] = np.where(room_plus[neither] >= room_minus[neither], 1.0, -1.0)
        self.side[ids] = side
        self.direction[ids] = side[:, None] * left
        self.until[ids] = now + cfg.hold_s + cfg.hold_growth_s * self.count[ids]
        self.count[ids] += 1


def _heading(state: np.ndarray) -> np.ndarray:
    """Yaw (M,) of states (M, S) from their row-major R_wb columns (R10 and R00)."""
    r = state[:, ROT_COLUMNS].astype(np.float64)
    return np.arctan2(r[:, 3], r[:, 0])


def _with_goal_direction(state: np.ndarray, i: np.ndarray, e: np.ndarray) -> np.ndarray:
    """A copy of ``state`` whose rows ``i`` read a far goal along world unit directions ``e`` (M, 2).

    The goal input is the heading-frame offset over max(|offset|, 10 m): a unit vector, Rz(-psi) e.
    """
    out = state.copy()
    psi = _heading(state[i])
    c, s = np.cos(psi), np.sin(psi)
    out[i, GOAL_COLUMNS.start] = c * e[:, 0] + s * e[:, 1]
    out[i, GOAL_COLUMNS.start + 1] = -s * e[:, 0] + c * e[:, 1]
    return out


def _room(p: np.ndarray, e: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance (M,) from points ``p`` (M, 2) along unit directions ``e`` (M, 2) to a rectangle's boundary.

    The rectangle is ``[lo, hi]``; a point outside it has 0, a zero direction inf.
    """
    lo, hi = np.broadcast_to(lo, p.shape), np.broadcast_to(hi, p.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(e > 1e-12, (hi - p) / e, np.where(e < -1e-12, (lo - p) / e, np.inf))
    return np.maximum(t.min(axis=1), 0.0)
