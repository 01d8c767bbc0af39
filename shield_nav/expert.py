"""The privileged planning expert: geodesic path, braking-aware speed profile, lag-anticipating tracker.

Every control step, for every env at once (the path trace and the elastic band are numba passes over envs and path
samples, the rest numpy over envs):

1. **Path.** From the vehicle's position, trace ``K = horizon / ds`` steps of length ``ds`` down the geodesic field
   of the episode's goal anchor, built with obstacles inflated by ``field_radius`` (so the shortest paths keep that
   clearance). Each step follows ``u = -grad Phi / |grad Phi|`` (central differences of step ``fd_step``), bent away
   from obstacles by ``clearance_gain * max(d_pref - d, 0) / d_pref`` times the part of ``grad d`` (ESDF gradient)
   normal to ``u``, so where there is room the path keeps ``d_pref`` of clearance. Within ``goal_switch`` of the
   goal (by Phi) the step goes straight at the goal point. Where the inflation closes every way to the goal (its Phi
   is flat at the vehicle), the path descends the *narrow field* instead: the env's own traversable space (vehicle
   radius), with a Dijkstra that weighs low clearance (``narrow_clearance``, ``narrow_weight``), so it keeps to the
   middle of narrow corridors.
2. **Speed profile.** The curvature at sample ``k`` is the turning angle between the tangents ``curv_window``
   samples before and after it, over that arc length (a kink the vehicle cannot follow anyway is spread over the
   window). The speed cap there is ``min(v_target, sqrt(lat_accel / kappa), clear_gain * (d - r_vehicle))``;
   a backward pass ``v_k <= sqrt(v_{k+1}^2 + 2 brake_accel ds)`` makes every cap reachable by braking, so the
   vehicle never arrives at a turn or a gap faster than it can take it. With ``visibility: camera`` the caps beyond
   the first path sample the depth camera cannot see are ``min_speed``: the profile plans only on what is in view.
3. **Tracker.** The attitude loop acts ``lag_s`` after a command (measured from the vehicle's step response,
   docs/expert.md), so the reference is read ``|v| lag_s`` along the path: speed ``v_r`` there, direction the chord
   to the point ``max(lookahead_min, |v| lookahead_s)`` ahead (pure pursuit pulls back onto the path), and the
   feedforward acceleration ``v_r d(v t)/ds`` (centripetal and along-track). The command is
   ``a = a_ff + k_v (v_ref - v)``, turned into thrust and attitude with the tilt and thrust limits of
   :class:`shield_nav.tracking.TrackingConfig` overridden by ``max_tilt_deg``. Yaw follows the chord, so the
   camera looks along the path. ``drag_ff`` > 0 adds that share of the vehicle model's drag at the current velocity
   (:func:`drag_accel`) to ``a``; off by default (docs/expert.md, "The drag feedforward"). That is the ``chord`` /
   ``tangent`` family. ``tracker: preview`` instead chooses ``a`` by receding-horizon LQ tracking of the path timed
   by its profile, on the inner loop's first-order model (:mod:`shield_nav.preview`). The default since
   2026-11-29, ``tracker: mppi``, samples input sequences round that preview command and scores their predictions
   on the same model against the timed path *and the ESDF*, so the command keeps clear of obstacles the plan passes
   close to (:mod:`shield_nav.mppi`). Envs that descend the narrow field keep the ``tangent`` command under both.

With ``commit_dist`` 0 the expert is stateless: its command depends only on the current state, so it labels any
state a student reaches (DAgger). With route hysteresis (``commit_dist`` > 0) it also remembers each env's last path;
it is called once per env step in evaluation and in DAgger's labelling alike, and an env whose episode starts again
(or a second call without a step between) gets the fresh trace. Velocity-keyed route choice (``predict_s`` > 0)
is the Markovian alternative: the route is chosen from position and velocity, no memory. It reads the map, so it is
**privileged**: an upper bound, not a competitor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numba
import numpy as np

from envs.config import require
from envs.fields.lookup import trilinear_batch, trilinear_point
from envs.vehicle.rotations import wrap_pi
from shield_nav.escape import CameraMap, EscapeConfig
from shield_nav.mppi import MppiTracker, clamp_inputs, path_integral_mean, rollout_costs
from shield_nav.preview import PreviewGains, timed_reference
from shield_nav.tracking import accel_to_command


@dataclass
class ExpertConfig:
    """Parameters of :class:`PlannerController` (``baselines.expert`` in an eval or train config)."""

    PRE_FIELD_VALUES: ClassVar[dict[str, Any]] = {
        "commit_dist": 0.0,
        "narrow_tangent": True,
        "band_iters": 0,
        "flat_test_inside": False,
    }
    """Fields added with a default that changed behaviour, and the value a config written before them means
    (:func:`envs.config.stored_config`): route hysteresis came on by default when it was added (2026-11-27), the
    sampling tracker in the mazes when ``narrow_tangent`` was (2026-12-03), the flatness test inside the scene's box
    when ``flat_test_inside`` was (2026-12-03, session 75); the elastic band was added off (2026-11-27) and came on
    by default later (2026-12-03), so a config written before the key means it off."""

    field_radius: float = 0.5
    """Obstacle inflation of the planning fields [m]; the geodesic paths keep this clearance where there is room."""
    flat_slope: float = 0.3
    """Below this largest |dPhi/dx| at the vehicle the inflated field is taken as flat (the inflation closes the way
    to the goal) and the narrow field is descended instead."""
    flat_test_inside: bool = True
    """True: the flatness test's points are kept inside the scene's box. Outside it the lookup adds the distance out
    of the box to Phi, a slope that is not the field's: at the box's side or top it hid a plateau, and the vehicle
    stalled there (session 75). False: the test as before (the shipped recipes' teacher)."""
    high_weight: float = 0.0
    """The inflated field's Dijkstra weighs each metre by ``1 + high_weight * max(0, z - high_ref)`` (``z`` above
    the scene's floor, m), so the expert's paths keep low where a low way is not much longer (0: off; for
    teaching: a teacher whose students do not climb over the clutter, docs/expert.md, "Low routes")."""
    high_ref: float = 1.5
    """Height above the scene's floor from which ``high_weight`` weighs the path [m]."""
    narrow_clearance: float = 0.6
    """The narrow field (descended where the inflated one is flat, e.g. in a maze of corridors narrower than twice
    ``field_radius``): the geodesic field of the env's own traversable space (the vehicle radius) whose Dijkstra
    weighs each metre by ``1 + narrow_weight * max(0, narrow_clearance - d) / narrow_clearance`` (``d`` the ESDF),
    so its paths keep to the middle of narrow corridors instead of grazing their walls [m] (0, or an env without
    goal anchors, ``episode.goal_anchors: 0``: the env's own field, unweighted)."""
    narrow_weight: float = 4.0
    """Weight of that clearance cost."""
    horizon: float = 14.0
    """Length of the traced path [m] (longer than the braking distance at the highest speed)."""
    ds: float = 0.35
    """Path sample spacing [m]."""
    fd_step: float = 0.2
    """Central-difference step of grad Phi [m]."""
    d_pref: float = 1.0
    """Preferred clearance (ESDF) of the path [m]: below it, each step is bent away from the nearest obstacle."""
    clearance_gain: float = 1.0
    """Strength of that bend (1: a step at the surface leaves at 45 degrees)."""
    goal_switch: float = 3.0
    """Below this geodesic distance to the goal, path steps go straight at the goal point [m]."""
    momentum: float = 0.5
    """Each step's direction is unit(u + momentum * previous step): damps the zig-zag that grad Phi shows along the
    boundary of the inflated obstacles (0: raw descent)."""
    smooth_window: int = 7
    """Samples of the centred moving average applied to the traced path (odd; 1: off). Where a smoothed sample comes
    closer than ``field_radius - smooth_slack`` to an obstacle, the raw sample is kept."""
    smooth_slack: float = 0.15
    """Clearance the smoothing may give up below ``field_radius`` [m]."""
    smooth_passes: int = 1
    """How many times the moving average (with its clearance check) is applied to the traced path."""
    band_iters: int = 10
    """Iterations of an elastic band run on the path after the moving average (0: off; 10 since 2026-12-03, with the
    ``mppi`` tracker; docs/expert.md, "The elastic band with the sampling tracker"). Each iteration moves every
    sample between the first and the last ``band_step`` of the way to the midpoint of its neighbours, then pushes a
    sample whose clearance (ESDF) is below ``band_clearance`` out along the ESDF gradient to it; a sample the
    iteration would leave closer to an obstacle than both that floor and its clearance before stays put. It lowers
    the path's curvature without cutting into the clearance the moving average gives up."""
    band_step: float = 0.5
    """Share of the way to the neighbours' midpoint that a band iteration moves a sample (0, 1]."""
    band_clearance: float = 0.5
    """Clearance floor of the band for paths on the inflated field [m]; paths on the narrow field keep the vehicle
    radius + ``smooth_slack``."""
    commit_dist: float = 1.0
    """Route hysteresis (0: off) [m]. The expert remembers each env's last path. Each step it also builds a
    *committed* path: from the vehicle onto the remembered path (merging over ``commit_blend``), along it for
    ``commit_dist`` metres beyond the vehicle, then down the field again from there (:func:`resample_ahead`). It flies
    the committed path instead of the fresh trace when the vehicle is within ``commit_max_dev`` of the remembered
    path, the committed path's clearance keeps the fresh one's floor (its smallest clearance, or the smoothing floor
    if that is lower), and it is at most ``commit_slack`` longer (arc length plus the geodesic distance left at its
    end). Near the ridge between two ways round an obstacle the fresh trace flips from one to the other between
    steps; the committed path keeps the way already begun until ``commit_dist`` ahead."""
    predict_s: float = 0.0
    """Velocity-keyed route choice (0: off) [s], a Markovian alternative to ``commit_dist`` (use one of the two).
    Each step a second path is traced from where the vehicle will be in ``predict_s`` at its current velocity: the
    straight segment to ``x + v predict_s``, then down the field from there. Where that path goes another way than
    the fresh trace (a sample of the fresh trace within ``route_span`` metres lies more than ``route_tol`` from it),
    it is flown instead, if it keeps the fresh trace's floor of clearance and is at most ``commit_slack`` longer.
    Near the ridge between two ways round an obstacle the choice then follows the side the vehicle already moves
    to, so a command toward one side keeps choosing it; the label stays a function of position and velocity."""
    predict_min_speed: float = 0.0
    """Velocity-keyed route choice only for envs whose target speed is at least this [m/s] (0: every env); the
    others fly the fresh trace, as with ``predict_s`` 0."""
    route_tol: float = 0.5
    """How far [m] the velocity-keyed path must leave the fresh trace to count as another way (``predict_s``)."""
    route_span: float = 4.0
    """Arc length [m] of the fresh trace compared with the velocity-keyed path (``predict_s``)."""
    commit_max_dev: float = 0.6
    """Farthest the vehicle may be from the remembered path for the committed path to be considered [m]."""
    commit_blend: float = 1.5
    """Over how many metres the committed path merges from the vehicle onto the remembered path [m]."""
    commit_slack: float = 1.0
    """How much longer than the fresh trace the committed path may be [m]."""
    curv_window: int = 3
    """Samples on either side over which the turning angle is measured (curvature = angle / arc length)."""
    lat_accel: float = 10.5
    """Lateral acceleration the speed profile allows in turns [m/s^2] (12 before route hysteresis, 2026-11-27; 8 with
    the ``tangent`` tracker until 2026-11-29)."""
    brake_accel: float = 8.0
    """Deceleration the speed profile plans with [m/s^2] (6 until 2026-11-29)."""
    accel_budget: float = 0.0
    """Horizontal acceleration that turning and braking share in the speed profile's backward pass [m/s^2] (a
    friction circle, :func:`speed_profile`; at most ``brake_accel`` of it brakes). 0: off, the two are separate
    budgets (``lat_accel`` in bends, ``brake_accel`` everywhere). The tilt cap gives about g tan(max_tilt_deg)."""
    clear_gain: float = 0.0
    """Speed cap per metre of clearance beyond the vehicle radius along the path [1/s] (0: off)."""
    min_speed: float = 1.0
    """Floor of the speed profile [m/s] (keeps the vehicle moving in tight spots)."""
    lag_s: float = 0.08
    """Command-to-acceleration lag of the inner loop the tracker anticipates [s]."""
    lookahead_s: float = 0.3
    """Pure-pursuit look-ahead time [s]."""
    lookahead_min: float = 1.0
    """Pure-pursuit look-ahead floor [m]."""
    tracker: str = "mppi"
    """Reference direction: ``chord`` (pure pursuit: towards the path point ``max(lookahead_min, |v| lookahead_s)``
    ahead; cuts inside bends by the chord's sagitta) or ``tangent`` (the path's direction between the reference
    sample and ``tangent_span`` samples after it, plus ``k_x`` times the offset of the reference sample from the
    position predicted ``lag_s`` ahead); or ``preview``: receding-horizon LQ tracking of the timed path on the
    attitude loop's first-order model (:mod:`shield_nav.preview`, keys ``preview_*``), except in envs that descend
    the narrow field (box mazes, where the path can shrink and turn from step to step at a crawl), which get the
    ``tangent`` command; or ``mppi``: sampled input sequences round the ``preview`` command, scored on the same
    model against the timed path and the ESDF (:mod:`shield_nav.mppi`, keys ``mppi_*``), the narrow field again on
    ``tangent``."""
    tangent_span: int = 2
    """Samples over which the ``tangent`` tracker measures the path direction."""
    k_x: float = 2.0
    """Cross-track gain of the ``tangent`` tracker [1/s]."""
    k_v: float = 4.0
    """Velocity-error gain [1/s]."""
    ff_gain: float = 0.5
    """Weight of the feedforward acceleration (0: pure velocity tracking)."""
    ff_window: int = 6
    """Samples over which the feedforward d(v t)/ds is differenced (a one-sample difference is noise)."""
    drag_ff: float = 0.0
    """Weight of the drag feedforward: the vehicle model's nominal drag at the current velocity (rotor drag in the
    body frame and parasitic drag, ``vehicle.airframe``) added to the commanded acceleration, so the velocity loop
    does not settle ``drag / k_v`` short of the reference (0: off)."""
    preview_tau: float = 0.2
    """``preview``: time constant of the model's thrust-vector response [s] (a fit gave 0.15 s after a 20 ms delay,
    docs/lab-log.md 2026-11-27; 0.2 s, which also stands for the delay, tracked better on the screen of 2026-11-28)."""
    preview_dt: float = 0.04
    """``preview``: interval of the model's held inputs [s]."""
    preview_steps: int = 20
    """``preview``: intervals in the horizon (horizon = ``preview_steps * preview_dt``)."""
    preview_q_pos: float = 1.0
    """``preview``: weight of the position error [1/m^2]."""
    preview_q_vel: float = 0.3
    """``preview``: weight of the velocity error [s^2/m^2]."""
    preview_r_acc: float = 0.001
    """``preview``: weight of the commanded acceleration [s^4/m^2]."""
    preview_r_jerk: float = 0.003
    """``preview``: weight of each change of the command between intervals (the first from the acceleration now)."""
    preview_accel: float = 10.0
    """``preview``: acceleration with which the reference speeds up along the path from the current speed [m/s^2]."""
    preview_drag: float = 1.0
    """``preview``: share of the nominal drag (:func:`drag_accel`) the model carries as a known disturbance."""
    mppi_steps: int = 20
    """``mppi``: intervals in the sampling horizon (:mod:`shield_nav.mppi`; the intervals are ``preview_dt`` long and
    the model is the preview tracker's, ``preview_tau``, ``preview_drag``)."""
    mppi_samples: int = 64
    """``mppi``: sequences sampled per env and control step (the last plan and the nominal command among them)."""
    mppi_sigma: float = 1.5
    """``mppi``: standard deviation of the horizontal input noise [m/s^2]."""
    mppi_sigma_z: float = 1.0
    """``mppi``: standard deviation of the vertical input noise [m/s^2]."""
    mppi_hold: int = 4
    """``mppi``: intervals over which each noise draw is held (smooth samples)."""
    mppi_temperature: float = 0.05
    """``mppi``: lambda of the path-integral weights as a share of each env's cost spread."""
    mppi_q_pos: float = 1.0
    """``mppi``: weight of the position error to the timed reference [1/m^2]."""
    mppi_q_vel: float = 0.3
    """``mppi``: weight of the velocity error [s^2/m^2]."""
    mppi_r_acc: float = 0.001
    """``mppi``: weight of the inputs [s^4/m^2]."""
    mppi_clearance: float = 0.5
    """``mppi``: ESDF below which a predicted position pays ``mppi_w_clear`` per square metre [m]."""
    mppi_w_clear: float = 400.0
    """``mppi``: weight of the clearance shortfall [1/m^2]."""
    narrow_tangent: bool = False
    """True: envs that descend the narrow field (box mazes) fly the ``tangent`` command whatever ``tracker`` says
    (the behaviour until 2026-12-03, which cuts the inside of the mazes' right-angle turns). False: they fly the
    ``preview``/``mppi`` tracker's own command too, and with ``mppi`` its clearance term there reads
    ``mppi_narrow_clearance`` (docs/expert.md, "The sampling tracker in the mazes")."""
    mppi_narrow_clearance: float = 0.3
    """``mppi``: the clearance term's ESDF threshold for envs on the narrow field [m] (``mppi_clearance`` cannot
    be kept in corridors narrower than twice it)."""
    mppi_w_crash: float = 1000.0
    """``mppi``: cost of a predicted position closer than the vehicle's collision radius."""
    mppi_vert_accel: float = 5.0
    """``mppi``: largest vertical input the samples may use [m/s^2]."""
    mppi_below_tops: bool = False
    """``mppi``: the plane at the obstacles' top plus the collision radius (the scene's top ``bounds_hi.z``; above it
    the vehicle's sphere passes over every obstacle, the evaluation's ``flew_over``) counts as a ceiling in the
    rollout cost, so the sampled command does not climb over the clutter where it is tight (the volume allows 1 m
    more; docs/expert.md, "Below the tops")."""
    max_tilt_deg: float = 50.0
    """Tilt cap of the commanded thrust vector [deg] (the vehicle clamps at 50; 48 until 2026-11-29)."""
    yaw_in_action: bool = False
    """Hold the yaw reference within the policy's action range: at most ``action.yaw_range_deg`` from the env's yaw
    base (``env.yaw_bases``), with roll and pitch solved at that yaw, so the thrust vector is the tracker's. Off
    (default): the yaw follows the path's chord however far it leads, and a DAgger label, clipped into the action
    range afterwards, turns the thrust vector with the cut yaw (docs/training.md, "Expert DAgger")."""
    camera_map: EscapeConfig = field(default_factory=lambda: EscapeConfig(kind="map", map_inflate=0.5, goal_radius=2.0))
    """The ``expert_cammap`` row only (:class:`CameraMapPlanner`): the map of what the flight's own camera has shown
    whose field its path descends instead of the scene's (its ``map_*`` keys, ``replan_s`` and ``goal_radius``, the
    field's goal disc; obstacles inflated by 0.5 m as the expert's own field is)."""
    visibility: str = "map"
    """What the speed profile may plan on. ``map``: the whole path, including bends round obstacles the camera does
    not show yet (privileged look-ahead). ``camera``: the path only up to its first sample the depth camera cannot
    see (outside its field of view or range, or with an obstacle on the line of sight by the ESDF); from there the
    cap is ``min_speed``, so the expert can always brake to a crawl before space it has not seen."""
    los_step: float = 0.5
    """Spacing [m] of the points checked on each line of sight (``visibility: camera``): the line is clear when the
    ESDF at every point exceeds half the spacing, so the balls round the points cover it."""

    def validate(self, prefix: str = "") -> None:
        """Positive lengths, gains and limits, naming the key."""
        for name in (
            "horizon",
            "ds",
            "fd_step",
            "d_pref",
            "lat_accel",
            "brake_accel",
            "k_v",
            "lookahead_min",
            "flat_slope",
            "ff_window",
            "preview_tau",
            "preview_dt",
            "preview_accel",
            "mppi_sigma",
            "mppi_temperature",
            "mppi_vert_accel",
        ):
            require(getattr(self, name) > 0, f"{prefix}{name}", f"must be > 0, got {getattr(self, name)}")
        for name in ("field_radius", "clearance_gain", "goal_switch", "clear_gain", "min_speed", "lag_s",
                     "lookahead_s", "ff_gain", "momentum", "smooth_slack", "narrow_clearance",
                     "narrow_weight", "drag_ff", "commit_dist", "commit_max_dev", "commit_blend",
                     "commit_slack", "predict_s", "predict_min_speed", "route_tol", "preview_q_pos",
                     "preview_q_vel", "preview_r_acc", "preview_r_jerk", "preview_drag",
                     "accel_budget", "mppi_sigma_z", "mppi_q_pos", "mppi_q_vel", "mppi_r_acc",
                     "mppi_clearance", "mppi_w_clear", "mppi_w_crash", "mppi_narrow_clearance", "high_weight",
                     "high_ref"):  # fmt: skip
            require(getattr(self, name) >= 0, f"{prefix}{name}", f"must be >= 0, got {getattr(self, name)}")
        require(self.smooth_window >= 1 and self.smooth_window % 2 == 1, f"{prefix}smooth_window",
                f"must be an odd number >= 1, got {self.smooth_window}")  # fmt: skip
        require(self.band_iters >= 0, f"{prefix}band_iters", f"must be >= 0, got {self.band_iters}")
        require(0 < self.band_step <= 1, f"{prefix}band_step", f"must be in (0, 1], got {self.band_step}")
        require(self.band_clearance >= 0, f"{prefix}band_clearance", f"must be >= 0, got {self.band_clearance}")
        require(self.smooth_passes >= 1, f"{prefix}smooth_passes", f"must be >= 1, got {self.smooth_passes}")
        longest = self.horizon - 2 * self.ds
        require(self.commit_dist < longest, f"{prefix}commit_dist",
                f"must be shorter than horizon - 2 ds ({longest:g} m), got {self.commit_dist}")  # fmt: skip
        require(self.route_span > 0, f"{prefix}route_span", f"must be > 0, got {self.route_span}")
        require(not (self.predict_s > 0 and self.commit_dist > 0), f"{prefix}predict_s",
                f"velocity-keyed route choice (predict_s {self.predict_s}) and route hysteresis (commit_dist "
                f"{self.commit_dist}) exclude each other: set one of them to 0")  # fmt: skip
        require(self.predict_min_speed == 0 or self.predict_s > 0, f"{prefix}predict_min_speed",
                f"gates the velocity-keyed route choice, which is off (predict_s 0): set predict_s > 0 or "
                f"predict_min_speed to 0, got {self.predict_min_speed}")  # fmt: skip
        require(self.curv_window >= 1, f"{prefix}curv_window", f"must be >= 1, got {self.curv_window}")
        require(self.horizon / self.ds >= 2 * self.curv_window + 2, f"{prefix}horizon",
                "must hold at least 2 * curv_window + 2 samples of ds")  # fmt: skip
        require(0 < self.max_tilt_deg < 60, f"{prefix}max_tilt_deg", "must be in (0, 60)")
        require(self.accel_budget == 0 or self.lat_accel <= self.accel_budget, f"{prefix}accel_budget",
                f"must be 0 (off) or at least lat_accel ({self.lat_accel}), got {self.accel_budget}")  # fmt: skip
        require(self.tracker in TRACKERS, f"{prefix}tracker", f"unknown tracker {self.tracker!r}; expected one of "
                f"{TRACKERS}")  # fmt: skip
        require(self.preview_steps >= 1, f"{prefix}preview_steps", f"must be >= 1, got {self.preview_steps}")
        require(self.preview_q_pos + self.preview_q_vel > 0, f"{prefix}preview_q_pos",
                "preview_q_pos + preview_q_vel must be > 0 (nothing would be tracked)")  # fmt: skip
        require(self.preview_r_acc + self.preview_r_jerk > 0, f"{prefix}preview_r_acc",
                "preview_r_acc + preview_r_jerk must be > 0 (the problem would have no unique minimiser)")  # fmt: skip
        require(self.mppi_steps >= 1, f"{prefix}mppi_steps", f"must be >= 1, got {self.mppi_steps}")
        require(self.mppi_samples >= 3, f"{prefix}mppi_samples", f"must be >= 3, got {self.mppi_samples}")
        require(self.mppi_hold >= 1, f"{prefix}mppi_hold", f"must be >= 1, got {self.mppi_hold}")
        require(self.tangent_span >= 1, f"{prefix}tangent_span", f"must be >= 1, got {self.tangent_span}")
        require(self.k_x >= 0, f"{prefix}k_x", f"must be >= 0, got {self.k_x}")
        require(self.visibility in VISIBILITIES, f"{prefix}visibility", f"unknown visibility {self.visibility!r}; "
                f"expected one of {VISIBILITIES}")  # fmt: skip
        require(self.los_step > 0, f"{prefix}los_step", f"must be > 0, got {self.los_step}")
        self.camera_map.validate(f"{prefix}camera_map.")


@numba.njit(cache=True, fastmath=False)
def _unit3(x: float, y: float, z: float) -> tuple[float, float, float]:
    n = max(math.sqrt(x * x + y * y + z * z), 1e-9)
    return x / n, y / n, z / n


@numba.njit(cache=True, fastmath=False)
def _phi_at(i: int, x: float, y: float, z: float, fallback: np.ndarray, p: tuple, q: tuple, g: np.ndarray) -> float:
    """Phi of env ``i`` at one point: the inflated field ``p``, or the narrow field ``q`` where ``fallback[i]``.

    ``g`` is any (M, 3) array (the lookup's unused gradient argument must type as one).
    """
    f = q if fallback[i] else p
    return trilinear_point(f[0][i], x, y, z, f[1], f[2], f[3], f[4], f[5], g, f[5], False, False, True)[4]


@numba.njit(cache=True, fastmath=False, parallel=True)
def _trace_kernel(
    x0: np.ndarray,
    goal: np.ndarray,
    fallback: np.ndarray,
    k_steps: int,
    h: float,
    ds: float,
    clearance_gain: float,
    d_pref: float,
    goal_switch: float,
    momentum: float,
    e: tuple,
    p: tuple,
    q: tuple,
    path: np.ndarray,
    clear: np.ndarray,
) -> None:
    """The path trace of :meth:`PlannerController.trace` for every env, envs split over numba's threads.

    Fields are tuples ``(index (N,), offset, shape, origin, res, values)``; ``e`` holds the ESDF and then its gradient.
    """
    for i in numba.prange(x0.shape[0]):  # envs are independent: numba's threads split them
        x, y, z = x0[i, 0], x0[i, 1], x0[i, 2]
        px = py = pz = 0.0
        for k in range(k_steps + 1):
            path[i, k, 0], path[i, k, 1], path[i, k, 2] = x, y, z
            d, gx, gy, gz, _ = trilinear_point(e[0][i], x, y, z, e[1], e[2], e[3], e[4], e[5], e[6], e[5],
                                               True, True, False)  # fmt: skip
            clear[i, k] = d
            if k == k_steps:
                break
            ux, uy, uz = _unit3(
                -(_phi_at(i, x + h, y, z, fallback, p, q, e[6]) - _phi_at(i, x - h, y, z, fallback, p, q, e[6])),
                -(_phi_at(i, x, y + h, z, fallback, p, q, e[6]) - _phi_at(i, x, y - h, z, fallback, p, q, e[6])),
                -(_phi_at(i, x, y, z + h, fallback, p, q, e[6]) - _phi_at(i, x, y, z - h, fallback, p, q, e[6])),
            )
            gx, gy, gz = _unit3(gx, gy, gz)
            gu = gx * ux + gy * uy + gz * uz
            w = clearance_gain * min(max(d_pref - d, 0.0), d_pref) / d_pref
            ux, uy, uz = _unit3(ux + w * (gx - gu * ux), uy + w * (gy - gu * uy), uz + w * (gz - gu * uz))
            if _phi_at(i, x, y, z, fallback, p, q, e[6]) < goal_switch:
                ux, uy, uz = _unit3(goal[i, 0] - x, goal[i, 1] - y, goal[i, 2] - z)
            if k > 0 and momentum > 0:
                ux, uy, uz = _unit3(ux + momentum * px, uy + momentum * py, uz + momentum * pz)
            px, py, pz = ux, uy, uz
            x, y, z = x + ds * ux, y + ds * uy, z + ds * uz


@numba.njit(cache=True, fastmath=False, parallel=True)
def _band_kernel(
    p: np.ndarray,
    d: np.ndarray,
    ids: np.ndarray,
    floor: np.ndarray,
    iters: int,
    step: float,
    offset: np.ndarray,
    shape: np.ndarray,
    origin: np.ndarray,
    res: np.ndarray,
    esdf: np.ndarray,
    grad: np.ndarray,
    phi: np.ndarray,
    yes: bool,
    no: bool,
) -> None:
    """The elastic band of :meth:`PlannerController._band`, in place on paths ``p`` (N, K+1, 3) and clearances ``d``.

    Each iteration: every inner sample moves ``step`` of the way to its neighbours' midpoint (Jacobi, from the
    previous iterate), a sample whose ESDF is below its env's ``floor`` is pushed out along the unit ESDF gradient
    by the shortfall, and a moved sample is kept where its ESDF is at least ``min(floor, d)``. The ESDF and its
    gradient come from the lookup's own batched pass (:func:`envs.fields.lookup.trilinear_batch`, as
    :meth:`FieldStack.esdf` reads them), and the arithmetic is numpy's order of operations, so the result is the
    numpy formulation's to the bit (tests/shield_nav/test_planner_expert.py). The lookup's want-flags come in as
    arguments (``yes`` True, ``no`` False), not literals: with literal flags LLVM specialises the fastmath lookup
    inlined here and its ESDF rounds 1 ulp away from :meth:`FieldStack.esdf`'s.
    """
    n, kp1 = d.shape
    for i in numba.prange(n):  # envs are independent: numba's threads split them
        sid = ids[i * kp1 : (i + 1) * kp1]
        q = np.empty((kp1, 3))
        dq = np.empty(kp1)
        g = np.empty((kp1, 3))
        none1 = np.empty(0)
        none3 = np.empty((0, 3))
        for _ in range(iters):
            for c in range(3):
                q[0, c] = p[i, 0, c]
                q[kp1 - 1, c] = p[i, kp1 - 1, c]
            for k in range(1, kp1 - 1):
                for c in range(3):
                    q[k, c] = p[i, k, c] + step * (0.5 * (p[i, k - 1, c] + p[i, k + 1, c]) - p[i, k, c])
            trilinear_batch(sid, q, offset, shape, origin, res, esdf, grad, phi, yes, no, no, dq, none3, none1)
            trilinear_batch(sid, q, offset, shape, origin, res, esdf, grad, phi, no, yes, no, none1, g, none1)
            for k in range(1, kp1 - 1):
                push = max(floor[i] - dq[k], 0.0)
                gn = max(math.sqrt(g[k, 0] * g[k, 0] + g[k, 1] * g[k, 1] + g[k, 2] * g[k, 2]), 1e-9)
                for c in range(3):
                    q[k, c] = q[k, c] + push * (g[k, c] / gn)
            trilinear_batch(sid, q, offset, shape, origin, res, esdf, grad, phi, yes, no, no, dq, none3, none1)
            for k in range(kp1):
                if dq[k] >= min(floor[i], d[i, k]) - 1e-9:
                    d[i, k] = dq[k]
                    for c in range(3):
                        p[i, k, c] = q[k, c]


TRACKERS = ("chord", "tangent", "preview", "mppi")
"""Reference directions of the tracker (:attr:`ExpertConfig.tracker`)."""

VISIBILITIES = ("map", "camera")
"""What the speed profile may plan on (:attr:`ExpertConfig.visibility`)."""


def yaw_within(psi: np.ndarray, base: np.ndarray, range_deg: float) -> np.ndarray:
    """Yaws ``psi`` (N,) [rad] held within ``range_deg`` of ``base`` (N,).

    ``base + clip(wrap(psi - base), -range, range)`` where the lead is beyond the range, ``psi`` itself where not.
    """
    r = math.radians(range_deg)
    psi = np.asarray(psi, dtype=np.float64)
    lead = wrap_pi(psi - base)
    return np.where(np.abs(lead) <= r, psi, base + np.clip(lead, -r, r))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def drag_accel(vel: np.ndarray, R_wb: np.ndarray, airframe: Any) -> np.ndarray:
    """The nominal drag acceleration (N, 3) [m/s^2] of the vehicle model at world velocities (N, 3).

    Rotor drag ``-R diag(d) R^T v`` (``airframe.linear_drag``, body frame) plus parasitic drag
    ``-rho C_d A |v| v / (2 m)`` (docs/vehicle.md).
    """
    v_b = np.einsum("nji,nj->ni", R_wb, vel)  # R^T v
    a = -np.einsum("nij,nj->ni", R_wb, np.asarray(airframe.linear_drag) * v_b)
    k = 0.5 * airframe.air_density * airframe.quadratic_drag_area / airframe.mass
    return a - k * np.linalg.norm(vel, axis=1, keepdims=True) * vel


def _project(points: np.ndarray, paths: np.ndarray) -> tuple:
    """Feet of the perpendiculars from points (N, 3) onto every segment of their polylines (N, K+1, 3).

    Returns ``(feet (N, K, 3), distances (N, K), t (N, K) in [0, 1] along each segment, segment vectors (N, K, 3))``.
    """
    a, ab = paths[:, :-1], np.diff(paths, axis=1)
    t = np.einsum("nkd,nkd->nk", points[:, None] - a, ab) / np.maximum(np.einsum("nkd,nkd->nk", ab, ab), 1e-18)
    t = np.clip(t, 0.0, 1.0)
    feet = a + t[..., None] * ab
    return feet, np.linalg.norm(feet - points[:, None], axis=2), t, ab


def polyline_distance(points: np.ndarray, paths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) from each point (N, 3) to its polyline (N, K+1, 3), and a vertex index (N,).

    The index is the nearest segment's end closer to the foot of the perpendicular.
    """
    _, d, t, _ = _project(points, paths)
    seg = d.argmin(axis=1)
    rows = np.arange(len(points))
    return d[rows, seg], seg + (t[rows, seg] > 0.5)


def resample_ahead(points: np.ndarray, paths: np.ndarray, m: int, ds: float, blend: int) -> tuple:
    """Paths (N, m+1, 3) that start at the points (N, 3) and merge onto their polylines (N, K+1, 3).

    Sample k is the polyline's point ``k ds`` beyond the foot of the perpendicular from the point, plus the offset
    point - foot times ``max(0, 1 - k / blend)``: sample 0 is the point itself, and the offset is removed
    linearly over ``blend`` samples. Returns the paths, the distances (N,) to the polylines, and whether (N,) each
    polyline reaches ``m ds`` beyond its foot.
    """
    feet, d, t, ab = _project(points, paths)
    n = len(points)
    rows, seg = np.arange(n), d.argmin(axis=1)
    seglen = np.linalg.norm(ab, axis=2)
    cum = np.concatenate((np.zeros((n, 1)), np.cumsum(seglen, axis=1)), axis=1)
    s = cum[rows, seg, None] + t[rows, seg, None] * seglen[rows, seg, None] + ds * np.arange(m + 1)  # (N, m+1)
    reach = s[:, -1] <= cum[:, -1] + 1e-9
    idx = np.clip((cum[:, None, :] <= s[..., None]).sum(axis=2) - 1, 0, seglen.shape[1] - 1)
    r = rows[:, None]
    u = np.clip((s - cum[r, idx]) / np.maximum(seglen[r, idx], 1e-9), 0.0, 1.0)
    out = paths[r, idx] + u[..., None] * ab[r, idx]
    w = np.maximum(0.0, 1.0 - np.arange(m + 1) / max(blend, 1))
    out += w[None, :, None] * (points - feet[rows, seg])[:, None, :]
    return out, d[rows, seg], reach


def speed_profile(kappa: np.ndarray, cap: np.ndarray, lat_accel: float, brake_accel: float, ds: float,
                  min_speed: float, accel_budget: float = 0.0) -> np.ndarray:  # fmt: skip
    """Fastest speeds (N, K) along a path that respect the caps and can brake into each of them.

    ``v_k = max(min_speed, min(cap_k, sqrt(lat_accel / kappa_k)))``, then backwards
    ``v_k = min(v_k, sqrt(v_{k+1}^2 + 2 a_k ds))``: from any sample, braking reaches every later cap by the time it
    gets there. Without a budget (``accel_budget`` 0) ``a_k = brake_accel``. With one, turning and braking share it
    (a friction circle): ``a_k = min(brake_accel, sqrt(A^2 - (v_{k+1}^2 kappa)^2))`` with ``kappa`` the larger of the
    segment's two end curvatures, so a bend flown at ``A`` of lateral acceleration leaves nothing to brake with and
    the braking happens before it.
    """
    v = np.minimum(cap, np.sqrt(lat_accel / np.maximum(kappa, 1e-9)))
    v = np.maximum(v, min_speed)
    two_a_ds = 2.0 * brake_accel * ds
    if accel_budget > 0:
        kseg = np.maximum(kappa[:, :-1], kappa[:, 1:])
    for k in range(v.shape[1] - 2, -1, -1):
        if accel_budget > 0:  # braking left by the turn at the segment's slower end
            lat = v[:, k + 1] ** 2 * kseg[:, k]
            two_a_ds = 2.0 * np.minimum(brake_accel, np.sqrt(np.maximum(accel_budget**2 - lat**2, 0.0))) * ds
        v[:, k] = np.minimum(v[:, k], np.sqrt(v[:, k + 1] ** 2 + two_a_ds))
    return v


def windowed_curvature(path: np.ndarray, window: int) -> np.ndarray:
    """Curvature (N, K+1) at every sample of paths (N, K+1, 3) with spacing ~ds.

    At sample k: the angle between the tangents ``window`` segments before and after (clamped to the ends),
    divided by the arc length between their midpoints. A circle of radius R gives 1 / R.
    """
    seg = np.diff(path, axis=1)  # (N, K, 3)
    seglen = np.linalg.norm(seg, axis=2)
    tan = seg / np.maximum(seglen, 1e-9)[..., None]
    n_seg = seg.shape[1]
    idx = np.arange(n_seg + 1)
    a = np.clip(idx - window, 0, n_seg - 1)
    b = np.clip(idx + window - 1, 0, n_seg - 1)
    cos = np.clip(np.einsum("nkc,nkc->nk", tan[:, a], tan[:, b]), -1.0, 1.0)
    angle = np.arccos(cos)
    cum = np.concatenate((np.zeros((len(path), 1)), np.cumsum(seglen, axis=1)), axis=1)
    mid = 0.5 * (cum[:, :-1] + cum[:, 1:])  # arc length at each segment's midpoint (N, K)
    arc = np.maximum(mid[:, b] - mid[:, a], 1e-9)
    return np.where(b > a, angle / arc, 0.0)


def visible_samples(path: np.ndarray, cam_pos: np.ndarray, R_wc: np.ndarray, cam: Any, esdf: Any,
                    los_step: float) -> np.ndarray:  # fmt: skip
    """Which path samples (N, K+1) the depth camera sees: in its frustum and range, with a free line of sight.

    Args:
        path: Paths (N, K+1, 3) in the frame of ``cam_pos``.
        cam_pos: Optical centres (N, 3).
        R_wc: Camera rotations (N, 3, 3), columns the optical axes (x right, y down, z forward) in that frame.
        cam: A :class:`envs.camera.CameraConfig` (``hfov_deg``, ``vfov_deg``, ``max_range``).
        esdf: ``esdf(points (N, M, 3)) -> (N, M)`` signed distance to the obstacles (> 0 free).
        los_step: Largest spacing of the points checked on a line of sight [m].

    A sample is seen when its z-depth is in ``(0, max_range]``, it is inside the horizontal and vertical field of
    view, and its line of sight is clear: ``m = ceil(max_range / los_step)`` points evenly inside the segment from
    the camera, spacing ``s = |segment| / (m + 1)``, each with ESDF above ``s / 2`` (the balls cover the segment, so
    no obstacle can hide between two points). Sample 0 (the vehicle) is always seen.
    """
    n, kp1, _ = path.shape
    rel = path - cam_pos[:, None, :]
    pc = np.einsum("nji,nkj->nki", R_wc, rel)  # R_wc^T rel: camera-frame coordinates
    z = pc[..., 2]
    tan_h = math.tan(math.radians(cam.hfov_deg) / 2.0)
    tan_v = math.tan(math.radians(cam.vfov_deg) / 2.0)
    seen = (z > 0) & (z <= cam.max_range) & (np.abs(pc[..., 0]) <= z * tan_h) & (np.abs(pc[..., 1]) <= z * tan_v)
    m = max(1, math.ceil(cam.max_range / los_step))
    t = np.arange(1, m + 1) / (m + 1)
    pts = cam_pos[:, None, None, :] + t[None, None, :, None] * rel[:, :, None, :]  # (N, K+1, m, 3)
    d = np.asarray(esdf(pts.reshape(n, -1, 3))).reshape(n, kp1, m)
    half = 0.5 * np.linalg.norm(rel, axis=2) / (m + 1)
    seen &= (d > half[..., None]).all(axis=2)
    seen[:, 0] = True
    return seen


def flight_env(family: str, indices: list[int], scene_seed: int | None, speed: float, num_envs: int,
               seed: int = 0) -> Any:  # fmt: skip
    """A reset :class:`envs.navigation.NavigationEnv` for flying the expert in diagnostics.

    Rendering and the curriculum off, one target speed, the evaluation's time limit (1.5 x); ``scene_seed`` None
    keeps the family's own scenes.
    """
    from envs.navigation import NavigationEnv

    over = {"scenes.family": family, "scenes.indices": list(indices), "render_depth": False,
            "curriculum.enabled": False, "episode.target_speeds": [float(speed)], "episode.speed_range": [],
            "episode.timeout_factor": 1.5, "seed": seed}  # fmt: skip
    if scene_seed is not None:
        over["scenes.seed"] = scene_seed
    env = NavigationEnv(num_envs=num_envs, **over)
    env.reset(seed=seed)
    return env


class PlannerController:
    """The planning expert as an evaluation controller (row ``expert``; see the module docstring)."""

    privileged = True
    reads_depth = False

    def __init__(self, cfg: Any) -> None:  # noqa: D107
        self.cfg = cfg
        self.ec: ExpertConfig = cfg.expert
        self._own: tuple | None = None
        self._bounds: tuple | None = None  # (env, per-scene box corners): the flatness test, mppi_below_tops' cap
        self.last: dict[str, np.ndarray] = {}
        self.fallback = np.zeros(0, dtype=bool)
        """(N,) bool of the last trace: envs that descended the narrow field (the inflated one was flat)."""
        self.committed = np.zeros(0, dtype=bool)
        """(N,) bool of the last trace: envs that fly the committed path (``commit_dist``)."""
        self._memory: tuple | None = None
        ec = self.ec
        self.gains = (
            PreviewGains.build(
                ec.preview_tau,
                ec.preview_dt,
                ec.preview_steps,
                ec.preview_q_pos,
                ec.preview_q_vel,
                ec.preview_r_acc,
                ec.preview_r_jerk,
            )
            if ec.tracker in ("preview", "mppi")
            else None
        )
        self.mppi = (
            MppiTracker(ec.preview_tau, ec.preview_dt, ec.mppi_steps, ec.mppi_samples) if ec.tracker == "mppi" else None
        )

    def reset(self, env: Any) -> None:
        """Forget the remembered paths (``commit_dist``) and plans (``mppi``); the fields are built once and kept."""
        self._memory = None
        if self.mppi is not None:
            self.mppi.reset()

    # ------------------------------------------------------------------------------------------------ fields
    def _fields(self, env: Any) -> tuple[Any, Any, Any]:
        """The planning fields of ``env``, built once per env (lazily, for the scenes and goals flown).

        (FieldStack, GoalAnchorFields or None) with obstacles inflated by ``field_radius``, and the narrow field's
        GoalAnchorFields (None: the env's own).
        """
        if self._own is not None and self._own[0] is env:
            return self._own[1], self._own[2], self._own[3]
        from envs.fields import scene_field_stack
        from envs.fields.anchors import GoalAnchorFields

        ec = self.ec
        k = env.anchor_fields.count if env.anchor_fields is not None else 0
        high = (ec.high_ref, ec.high_weight) if ec.high_weight > 0 else None
        if high is not None and k == 0:
            raise ValueError("baselines.expert.high_weight needs goal anchor fields (episode.goal_anchors > 0)")
        if abs(ec.field_radius - env.cfg.vehicle.airframe.collision_radius) < 1e-9:
            stack = env.field_stack
            anchors = env.anchor_fields if high is None else GoalAnchorFields(env.scenes, stack, k, lazy=True,
                                                                               height_cost=high)  # fmt: skip
        else:
            stack = scene_field_stack(env.scenes, env.cfg.scenes.field_resolution, ec.field_radius)
            anchors = GoalAnchorFields(env.scenes, stack, k, lazy=True, height_cost=high) if k > 0 else None
        narrow = None
        if ec.narrow_clearance > 0 and k > 0:
            narrow = GoalAnchorFields(env.scenes, env.field_stack, k, lazy=True,
                                      clearance_cost=(ec.narrow_clearance, ec.narrow_weight))  # fmt: skip
        self._own = (env, stack, anchors, narrow)
        return stack, anchors, narrow

    def _phi(self, env: Any, ids: np.ndarray, anchor: np.ndarray, pts: np.ndarray, own: bool = True,
             rows: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """Phi at ``pts`` of the inflated fields (``own``) or of the narrow field (the env's traversable space).

        ``ids`` / ``anchor``: each point's scene and goal anchor; ``rows``: each point's env (read by subclasses
        whose fields are per flight, :class:`CameraMapPlanner`).
        """
        stack, anchors, narrow = self._fields(env)
        if not own:
            stack, anchors = env.field_stack, (narrow if narrow is not None else env.anchor_fields)
        if anchors is not None:
            return anchors.geodesic(ids, anchor, pts)
        return stack.geodesic(ids, pts)

    # ------------------------------------------------------------------------------------------------ planning
    def _phi_fields(self, env: Any, ids: np.ndarray, anchor: np.ndarray, own: bool = True,
                    rows: np.ndarray | None = None) -> tuple:  # fmt: skip
        """The fields :meth:`_phi` reads, as ``(index (N,), offset, shape, origin, res, phi)`` for a kernel."""
        stack, anchors, narrow = self._fields(env)
        if not own:
            stack, anchors = env.field_stack, (narrow if narrow is not None else env.anchor_fields)
        f = anchors.kernel_fields(ids, anchor) if anchors is not None else stack.kernel_fields(ids)
        return f[0], f[1], f[2], f[3], f[4], f[7]

    def trace(self, env: Any) -> tuple[np.ndarray, np.ndarray]:
        """Paths (N, K+1, 3) from every vehicle down the inflated geodesic field, and their ESDF (N, K+1).

        One numba pass over envs and path samples (``_trace_kernel``); the per-step rule is the module docstring's.
        """
        ec = self.ec
        n = env.num_envs
        ids, anchor = env.scene_id_buf, env.anchor_buf
        k_steps = int(math.ceil(ec.horizon / ec.ds))
        h = ec.fd_step
        x = env.local_pos.astype(np.float64)
        if not np.isfinite(x).all():
            bad = int(np.flatnonzero(~np.isfinite(x).all(axis=1))[0])
            raise ValueError(f"PlannerController.trace: env {bad} has a non-finite position {x[bad].tolist()}")
        # Where the inflation closes every way to the goal, the inflated Phi is flat (capped at its unreachable
        # value): those envs descend the narrow field instead (the vehicle radius, clearance-weighted). The test's
        # points are kept inside the scene's box: outside it the lookup adds the distance out to Phi, a slope that
        # is not the field's and that, at the box's side, hid a plateau (a stall in a box maze, session 75).
        offsets = np.concatenate((np.eye(3) * h, -np.eye(3) * h))  # (6, 3)
        pts = np.concatenate((x[:, None, :], x[:, None, :] + offsets[None]), axis=1)
        if ec.flat_test_inside:
            lo, hi = self._box(env)
            pts = np.clip(pts, lo[ids][:, None, :], hi[ids][:, None, :])
        pts = pts.reshape(-1, 3)
        every = np.arange(n)
        phi0 = self._phi(env, np.repeat(ids, 7), np.repeat(anchor, 7), pts, rows=np.repeat(every, 7)).reshape(n, 7)
        slope = np.abs(phi0[:, 1:4] - phi0[:, 4:7]).max(axis=1) / (2 * h)
        fallback = self._closed(env, slope)
        self.fallback = fallback
        p = self._phi_fields(env, ids, anchor, rows=every)
        q = p
        if fallback.any():  # the narrow field is built only for the envs that descend it
            qf = self._phi_fields(env, ids[fallback], anchor[fallback], own=False, rows=every[fallback])
            index = np.zeros(n, dtype=np.int64)
            index[fallback] = qf[0]
            q = (index, *qf[1:])
        ef = env.field_stack.kernel_fields(ids)
        fields = ((ef[0], *ef[1:7]), p, q)
        raw, raw_clear = self._descend(env, x, k_steps, fallback, fields)
        path, clear = self._refine(env, raw, raw_clear)
        if ec.commit_dist > 0:
            path, clear = self._commit(env, x, k_steps, fields, path, clear)
        elif ec.predict_s > 0:
            path, clear = self._velocity_key(env, x, k_steps, fields, path, clear)
        else:
            self.committed = np.zeros(n, dtype=bool)
        return path, clear

    def _closed(self, env: Any, slope: np.ndarray) -> np.ndarray:
        """(N,) bool: the envs that descend the narrow field.

        Those whose inflated field has no way from the vehicle: its largest slope ``slope`` (N,) there is below
        ``flat_slope``.
        """
        return slope < self.ec.flat_slope

    def _descend(self, env: Any, x: np.ndarray, k_steps: int, fallback: np.ndarray, fields: tuple) -> tuple:
        """Raw paths (N, k_steps+1, 3) from ``x`` (N, 3) down the fields (``_trace_kernel``), and their ESDF."""
        ec = self.ec
        n = len(x)
        path = np.empty((n, k_steps + 1, 3))
        clear = np.empty((n, k_steps + 1))
        _trace_kernel(np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(env.goal_buf, dtype=np.float64),
                      fallback, k_steps, ec.fd_step, ec.ds, ec.clearance_gain, ec.d_pref, ec.goal_switch, ec.momentum,
                      *fields, path, clear)  # fmt: skip
        return path, clear

    def _refine(self, env: Any, path: np.ndarray, clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The moving average (``smooth_passes`` times) and the elastic band, as configured."""
        ec = self.ec
        if ec.smooth_window > 1:
            for _ in range(ec.smooth_passes):
                path, clear = self._smooth(env, path, clear)
        if ec.band_iters > 0:
            path, clear = self._band(env, path, clear)
        return path, clear

    def _commit(self, env: Any, x: np.ndarray, k_steps: int, fields: tuple, path: np.ndarray,
                clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Route hysteresis (``commit_dist``): the committed path where it qualifies, else the fresh trace.

        Returns the path flown (remembered for the next step) and its clearance.
        """
        ec = self.ec
        n = env.num_envs
        ep = np.array(env.episode_length_buf, copy=True)
        take = np.zeros(n, dtype=bool)
        mem = self._memory
        if mem is not None and mem[0] is env and mem[1].shape == path.shape:
            prev, prev_ep = mem[1], mem[2]
            m = max(1, int(round(ec.commit_dist / ec.ds)))
            blend = max(1, int(round(ec.commit_blend / ec.ds)))
            head, dev, reach = resample_ahead(x, prev, m, ec.ds, blend)  # head[:, 0] is the vehicle
            ok = (ep > prev_ep) & (dev <= ec.commit_max_dev) & reach  # same episode, on the remembered path
            if ok.any():
                head = head[:, 1:]
                tail, tail_clear = self._descend(env, head[:, -1], k_steps - m, self.fallback, fields)
                tail, tail_clear = self._refine(env, tail, tail_clear)
                ids = np.repeat(env.scene_id_buf, m)
                head_clear = env.field_stack.esdf(ids, head.reshape(-1, 3)).reshape(n, m)
                b_path = np.concatenate((x[:, None], head, tail[:, 1:]), axis=1)
                b_cl = np.concatenate((clear[:, :1], head_clear, tail_clear[:, 1:]), axis=1)
                take = ok & self._may_replace(env, path, clear, b_path, b_cl)
                path = np.where(take[:, None, None], b_path, path)
                clear = np.where(take[:, None], b_cl, clear)
        self._memory = (env, path.copy(), ep)
        self.committed = take
        return path, clear

    def _velocity_key(self, env: Any, x: np.ndarray, k_steps: int, fields: tuple, path: np.ndarray,
                      clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Velocity-keyed route choice (``predict_s``): the predicted path where it goes another way and qualifies.

        The predicted path is the straight segment from ``x`` to ``x + v predict_s``, then the trace down the field
        from there, resampled every ``ds`` from ``x`` (:func:`resample_ahead`). Returns the path flown and its
        clearance; ``self.committed`` marks the envs that fly the predicted path.
        """
        ec = self.ec
        n = env.num_envs
        x_p = x + np.asarray(env.vehicles.vel_w, dtype=np.float64) * ec.predict_s
        tail, _ = self._descend(env, x_p, k_steps, self.fallback, fields)
        tail, _ = self._refine(env, tail, np.zeros(tail.shape[:2]))
        poly = np.concatenate((x[:, None], tail), axis=1)
        b_path, _, _ = resample_ahead(x, poly, k_steps, ec.ds, 1)
        ids = np.repeat(env.scene_id_buf, k_steps + 1)
        b_cl = env.field_stack.esdf(ids, b_path.reshape(-1, 3)).reshape(n, k_steps + 1)
        span = min(k_steps, max(1, int(round(ec.route_span / ec.ds))))
        # How far the fresh trace's first route_span metres leave the predicted path: its samples 1..span, each
        # against its env's predicted polyline.
        d, _ = polyline_distance(path[:, 1 : span + 1].reshape(-1, 3), np.repeat(b_path, span, axis=0))
        apart = d.reshape(n, span).max(axis=1)
        fast = np.asarray(env.target_speed_buf) >= ec.predict_min_speed
        take = fast & (apart > ec.route_tol) & self._may_replace(env, path, clear, b_path, b_cl)
        self.committed = take
        return np.where(take[:, None, None], b_path, path), np.where(take[:, None], b_cl, clear)

    def _may_replace(self, env: Any, path: np.ndarray, clear: np.ndarray, b_path: np.ndarray,
                     b_cl: np.ndarray) -> np.ndarray:  # fmt: skip
        """Whether (N,) the alternative path ``b_path`` may replace the fresh trace ``path``.

        It must keep the fresh trace's floor of clearance (its smallest, or the smoothing floor if that is lower) and be
        at most ``commit_slack`` longer (:meth:`_route_cost`).
        """
        ec = self.ec
        r_vehicle = env.cfg.vehicle.airframe.collision_radius
        floor = np.where(self.fallback, r_vehicle + ec.smooth_slack, ec.field_radius - ec.smooth_slack)
        safe = b_cl.min(axis=1) >= np.minimum(clear.min(axis=1), floor) - 1e-9
        return safe & (self._route_cost(env, b_path) <= self._route_cost(env, path) + ec.commit_slack)

    def _route_cost(self, env: Any, path: np.ndarray) -> np.ndarray:
        """Arc length of paths (N, K+1, 3) plus the geodesic distance left at their ends, on each env's field."""
        ids, anchor = env.scene_id_buf, env.anchor_buf
        length = np.linalg.norm(np.diff(path, axis=1), axis=2).sum(axis=1)
        end = path[:, -1]
        every = np.arange(len(end))
        left = self._phi(env, ids, anchor, end, rows=every)
        fb = self.fallback
        if fb.any():
            left[fb] = self._phi(env, ids[fb], anchor[fb], end[fb], own=False, rows=every[fb])
        return length + left

    def _band(self, env: Any, path: np.ndarray, clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Elastic band on the paths (``band_iters``); the first and last samples stay put (``_band_kernel``)."""
        ec = self.ec
        n, kp1, _ = path.shape
        ids = np.repeat(np.asarray(env.scene_id_buf, dtype=np.int64), kp1)
        r_vehicle = env.cfg.vehicle.airframe.collision_radius
        floor = np.where(self.fallback, r_vehicle + ec.smooth_slack, ec.band_clearance).astype(np.float64)
        fields = env.field_stack.kernel_fields(ids)
        p = np.array(path, dtype=np.float64, order="C")
        d = np.array(clear, dtype=np.float64, order="C")
        _band_kernel(p, d, ids, floor, ec.band_iters, ec.band_step, *fields[1:], True, False)
        return p, d

    def _smooth(self, env: Any, path: np.ndarray, clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centred moving average of the paths (window shrinks at the ends; the first sample stays put)."""
        ec = self.ec
        n, kp1, _ = path.shape
        half = ec.smooth_window // 2
        cum = np.concatenate((np.zeros((n, 1, 3)), np.cumsum(path, axis=1)), axis=1)
        k = np.arange(kp1)
        w = np.minimum(np.minimum(k, kp1 - 1 - k), half)
        smooth = (cum[:, k + w + 1] - cum[:, k - w]) / (2 * w + 1)[None, :, None]
        ids = np.repeat(env.scene_id_buf, kp1)
        d = env.field_stack.esdf(ids, smooth.reshape(-1, 3)).reshape(n, kp1)
        # Inflated paths may give up smooth_slack of their inflation; narrow-field paths keep smooth_slack above the
        # vehicle radius (they start at it).
        r_vehicle = env.cfg.vehicle.airframe.collision_radius
        floor = np.where(self.fallback, r_vehicle + ec.smooth_slack, ec.field_radius - ec.smooth_slack)
        keep = d >= floor[:, None]
        return np.where(keep[..., None], smooth, path), np.where(keep, d, clear)

    def plan(self, env: Any) -> dict[str, np.ndarray]:
        """Path, clearance, curvature and speed profile (N, K+1) for every env."""
        ec = self.ec
        path, clear = self.trace(env)
        kappa = windowed_curvature(path, ec.curv_window)
        cap = np.repeat(env.target_speed_buf[:, None], path.shape[1], axis=1)
        if ec.clear_gain > 0:
            margin = clear - env.cfg.vehicle.airframe.collision_radius
            cap = np.minimum(cap, ec.clear_gain * np.maximum(margin, 0.0))
        out = {"path": path, "clear": clear, "kappa": kappa}
        if ec.visibility == "camera":
            from envs.camera.model import camera_poses

            cam_pos, R_wc = camera_poses(env.cfg.camera, env.local_pos, env.vehicles.R_wb)
            ids = env.scene_id_buf

            def esdf(pts: np.ndarray) -> np.ndarray:
                flat = pts.reshape(-1, 3)
                return env.field_stack.esdf(np.repeat(ids, pts.shape[1]), flat).reshape(pts.shape[:2])

            seen = np.logical_and.accumulate(visible_samples(path, cam_pos, R_wc, env.cfg.camera, esdf,
                                                             ec.los_step), axis=1)  # fmt: skip
            cap = np.where(seen, cap, ec.min_speed)
            out["seen"] = seen
        out["speed"] = speed_profile(kappa, cap, ec.lat_accel, ec.brake_accel, ec.ds, ec.min_speed, ec.accel_budget)
        return out

    def commands(self, env: Any, among: np.ndarray | None = None) -> np.ndarray:
        """Commands (N, 4) = [f_n, phi, theta, psi] (see the module docstring)."""
        ec = self.ec
        plan = self.plan(env)
        path, v_prof = plan["path"], plan["speed"]
        n, kp1 = v_prof.shape
        rows = np.arange(n)
        pos, vel = env.local_pos, env.vehicles.vel_w
        speed = np.linalg.norm(vel, axis=1)
        seg = np.diff(path, axis=1)
        tan = _unit(seg)  # (N, K, 3)
        k_ref = np.clip(np.round(speed * ec.lag_s / ec.ds).astype(int), 0, kp1 - 3)
        k_la = np.clip(np.round(np.maximum(ec.lookahead_min, speed * ec.lookahead_s) / ec.ds).astype(int),
                       k_ref + 1, kp1 - 1)  # fmt: skip
        v_r = v_prof[rows, k_ref]
        if ec.tracker in ("tangent", "preview", "mppi"):  # the tangent command where the narrow field is flown
            k_b = np.minimum(k_ref + ec.tangent_span, kp1 - 1)
            chord = _unit(path[rows, k_b] - path[rows, k_ref])
            v_ref = v_r[:, None] * chord + ec.k_x * (path[rows, k_ref] - (pos + vel * ec.lag_s))
        else:
            chord = _unit(path[rows, k_la] - pos)
            v_ref = v_r[:, None] * chord
        # Feedforward d(v t)/dt = v d(v t)/ds at the reference sample.
        k_ff = np.minimum(k_ref + ec.ff_window, kp1 - 2)
        vt0 = v_prof[rows, k_ref, None] * tan[rows, k_ref]
        vt1 = v_prof[rows, k_ff, None] * tan[rows, k_ff]
        a_ff = ec.ff_gain * v_r[:, None] * (vt1 - vt0) / (np.maximum(k_ff - k_ref, 1) * ec.ds)[:, None]
        a = a_ff + ec.k_v * (v_ref - vel)
        if ec.drag_ff > 0:
            a = a - ec.drag_ff * drag_accel(vel, env.vehicles.R_wb, env.cfg.vehicle.airframe)
        if ec.tracker in ("preview", "mppi"):  # mppi samples round the preview command
            model = self._lag_model(env, plan)
            a_p, v_p = self._preview(model)
            if ec.tracker == "mppi":
                a_p = self._mppi(env, model, a_p)
            if ec.narrow_tangent:  # envs on the narrow field keep the tangent command
                wide = ~self.fallback[:, None]
                a, v_ref = np.where(wide, a_p, a), np.where(wide, v_p, v_ref)
            else:
                a, v_ref = a_p, v_p
        psi = np.arctan2(chord[:, 1], chord[:, 0])
        if ec.yaw_in_action:
            psi = yaw_within(psi, env.yaw_bases, env.cfg.action.yaw_range_deg)
        track = replace(self.cfg.tracking, max_tilt_deg=ec.max_tilt_deg)
        self.last = {**plan, "v_ref": v_ref, "a": a, "k_ref": k_ref}
        return accel_to_command(a, psi, track, env.cfg.vehicle.gravity)

    def _lag_model(self, env: Any, plan: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """What the preview and sampling trackers read, computed once per step.

        The inner-loop model's state ``x0`` (N, 3 axes, [p, v, a]), the thrust vector's acceleration now ``a_thr``
        (N, 3), the nominal drag ``drag`` (N, 3) and the timed reference ``ref_p``, ``ref_v`` (N, steps, 3) over the
        longer of their horizons.
        """
        ec = self.ec
        veh = env.vehicles
        vel = veh.vel_w
        a_thr = veh.R_wb[:, :, 2] * (veh.motor_thrust_buf.sum(axis=1) / veh.nominal_mass)[:, None]
        a_thr[:, 2] -= env.cfg.vehicle.gravity
        path, v_prof = plan["path"], plan["speed"]
        # The reference starts from the vehicle's speed along the path (not |v|: after a turn of the route the
        # vehicle does not yet move along it).
        ahead = _unit(path[:, min(ec.tangent_span, path.shape[1] - 1)] - path[:, 0])
        along = np.maximum(np.einsum("ni,ni->n", vel, ahead), 0.0)
        steps = max(ec.preview_steps, ec.mppi_steps) if ec.tracker == "mppi" else ec.preview_steps
        ref_p, ref_v = timed_reference(path, v_prof, along, ec.preview_accel, ec.preview_dt, steps)
        return {"x0": np.stack((env.local_pos, vel, a_thr), axis=2), "a_thr": a_thr, "ref_p": ref_p, "ref_v": ref_v,
                "drag": ec.preview_drag * drag_accel(vel, veh.R_wb, env.cfg.vehicle.airframe)}  # fmt: skip

    def _mppi(self, env: Any, model: dict[str, np.ndarray], nominal: np.ndarray) -> np.ndarray:
        """Accelerations (N, 3) of the ``mppi`` tracker (:mod:`shield_nav.mppi`) round the nominal command."""
        ec = self.ec
        m = self.mppi
        t = ec.mppi_steps
        base = m.warm_start(nominal, env.episode_length_buf, env.cfg.vehicle.command_dt)
        u = clamp_inputs(m.candidates(base, nominal, ec.mppi_sigma, ec.mppi_sigma_z, ec.mppi_hold),
                         env.cfg.vehicle.gravity, ec.max_tilt_deg, ec.mppi_vert_accel)  # fmt: skip
        ef = env.field_stack.kernel_fields(env.scene_id_buf)
        costs = np.empty(u.shape[:2])
        clearance = np.where(self.fallback, ec.mppi_narrow_clearance, ec.mppi_clearance)
        rollout_costs(np.ascontiguousarray(model["x0"]), u, np.ascontiguousarray(model["drag"]),
                      np.ascontiguousarray(model["ref_p"][:, :t]), np.ascontiguousarray(model["ref_v"][:, :t]),
                      m.a_mat, m.b_vec, m.e_vec, ec.mppi_q_pos, ec.mppi_q_vel, ec.mppi_r_acc, ec.mppi_w_clear,
                      clearance, ec.mppi_w_crash, env.cfg.vehicle.airframe.collision_radius, ef[:7],
                      costs, self._z_cap(env))  # fmt: skip
        m.plan = path_integral_mean(u, costs, ec.mppi_temperature)
        return m.plan[:, 0]

    def _box(self, env: Any) -> tuple[np.ndarray, np.ndarray]:
        """Per scene of ``env``, the lower and upper corners (S, 3) of its flight volume, in the scene's own frame."""
        if self._bounds is None or self._bounds[0] is not env:
            lo = np.array([sc.bounds_lo for sc in env.scenes], dtype=np.float64)
            hi = np.array([sc.bounds_hi for sc in env.scenes], dtype=np.float64)
            self._bounds = (env, lo, hi)
        return self._bounds[1], self._bounds[2]

    def _z_cap(self, env: Any) -> np.ndarray:
        """Per env, the height whose plane the sampling tracker treats as a ceiling.

        ``inf`` unless ``mppi_below_tops``; else the env's scene top ``bounds_hi.z`` plus the collision radius, in
        the scene's own frame (that of ``env.local_pos``, which the rollouts start from). The per-scene values are
        computed once per env (:meth:`_box`), as the fields are.
        """
        if not self.ec.mppi_below_tops:
            return np.full(env.num_envs, np.inf)
        return self._box(env)[1][env.scene_id_buf, 2] + env.cfg.vehicle.airframe.collision_radius

    def _preview(self, model: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Accelerations (N, 3) and first reference velocities (N, 3) of the ``preview`` tracker."""
        t = self.ec.preview_steps
        ref_p, ref_v = model["ref_p"][:, :t], model["ref_v"][:, :t]
        ref = np.stack((ref_p, ref_v), axis=2).transpose(0, 3, 1, 2).reshape(len(ref_p), 3, -1)  # (N, 3, 2 steps)
        return self.gains.first_input(ref, model["x0"], model["drag"], model["a_thr"]), ref_v[:, 0]


class CameraMapPlanner(PlannerController):
    """The planning expert routed by what its own camera has shown (the ``expert_cammap`` row; a diagnostic).

    Path tracer, elastic band, speed profile and sampling tracker are the expert's, and so is their ESDF (the
    scene's: privileged local geometry); only Phi, the field the path descends and the route cost reads, is each
    flight's own: a Dijkstra over the 2D map of its depth images (:class:`shield_nav.escape.CameraMap`, unmapped
    space free, mapped cells inflated by ``camera_map.map_inflate``, to a disc of ``camera_map.goal_radius`` round the
    goal), replanned every ``camera_map.replan_s`` and extended over the volume's height by the height difference to
    the goal (as the scene's field grows away from the goal's height). Where the vehicle stands within
    ``map_inflate`` of what it mapped, or that field is flat, the path descends the expert's narrow field built on the
    same map instead (:meth:`shield_nav.escape.CameraMap.narrow_field`: the vehicle radius, ``narrow_clearance``,
    ``narrow_weight``), and the tracker flies those flights as the expert flies its narrow-field ones. Against the
    ``expert`` row
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
