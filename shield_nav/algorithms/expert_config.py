"""The planning expert's parameters (:class:`ExpertConfig`): path, speed profile, tracker and visibility."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from envs.config import require
from shield_nav.safety.escape import EscapeConfig


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
    attitude loop's first-order model (:mod:`.preview`, keys ``preview_*``), except in envs that descend
    the narrow field (box mazes, where the path can shrink and turn from step to step at a crawl), which get the
    ``tangent`` command; or ``mppi``: sampled input sequences round the ``preview`` command, scored on the same
    model against the timed path and the ESDF (:mod:`.mppi`, keys ``mppi_*``), the narrow field again on
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
    """``mppi``: intervals in the sampling horizon (:mod:`.mppi`; the intervals are ``preview_dt`` long and
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


TRACKERS = ("chord", "tangent", "preview", "mppi")
"""Reference directions of the tracker (:attr:`ExpertConfig.tracker`)."""

VISIBILITIES = ("map", "camera")
"""What the speed profile may plan on (:attr:`ExpertConfig.visibility`)."""
