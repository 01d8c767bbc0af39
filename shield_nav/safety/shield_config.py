"""The shield's parameters (:class:`ShieldConfig`): barrier, gains, point selection, memory and map, altitude rows."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import qpsolvers

from envs.config import require
from shield_nav.safety.memory import DEPTH_FILTERS


@dataclass
class ShieldConfig:
    """HOCBF shield parameters. Acceleration units are m/s^2, lengths m."""

    PRE_FIELD_VALUES: ClassVar[dict[str, Any]] = {"map_seconds": 0.0}
    """Fields added with a default that changed behaviour, and the value a config written before them means
    (:func:`envs.config.stored_config`): the local map came on by default on 2026-11-30, and a shield stored without
    the key (the shipped Full's training-loop shield, an eval run's resumed config) flew without it."""

    alpha0: float = 64.0
    """HOCBF coefficient on B [1/s^2]. With alpha0 = p1 p2 and alpha1 = p1 + p2 (Xiao & Belta's HOCBF with class-K
    gains p1, p2) the defaults are p1 = p2 = 8 /s, chosen on the validation scenes with ``lag_s`` 0.15 s
    (docs/shield.md, "Tuning"). Larger values allow later, harder corrections (less conservative); smaller values
    brake earlier. A vehicle passing a point at lateral offset l and speed V with a = 0 violates the row when
    l^2 < r_safe^2 + 2 V^2 / p^2 (p1 = p2 = p): p = 2 /s triggers for every obstacle within 3.6 m of the path at
    5 m/s (docs/shield.md, "Gains" and "Tuning")."""
    alpha1: float = 16.0
    """HOCBF coefficient on Bdot [1/s]."""
    r_safe: float = 0.3
    """Safety radius [m] around every obstacle point: the vehicle's collision radius (0.2 m) plus 0.1 m of margin.
    Chosen on the validation scenes behind the Full policy (docs/shield.md, "Safety radius"): with a larger radius
    the shield brakes for points the flight would pass, and fast flights run out of time."""
    max_constraints: int = 8
    """K: obstacle constraints kept per step (the tightest sector minima, see ``select_constraints``)."""
    active_set_iterations: int = 8
    """After each QP, the whole cloud is checked at the corrected acceleration a*: if a point's row is violated
    (the selection ranked margins at the *raw* command, so the point that binds after the correction can have been
    dropped), the most violated row is added and the QP is solved again, up to this many times (a cutting-plane
    active set; docs/shield.md). 0: select once at the raw command (the paper's formulation, kept as a switch)."""
    active_set_tol: float = 0.01
    """Violation [m^2/s^2 of the HOCBF row] below which a point counts as satisfied in that check. A row is
    2 r.a >= b, so 0.01 is at most 0.01 m/s^2 of acceleration along r at r_safe = 0.5 m; a much smaller tolerance
    adds rounds for such slivers (docs/shield.md, "Cost")."""
    azimuth_sectors: int = 12
    """Azimuth bins of the direction from the vehicle to a point (world frame)."""
    elevation_sectors: int = 3
    """Elevation bins of that direction."""
    voxel: float = 0.0
    """If > 0, downsample the point cloud to this voxel edge [m] before selection (0: use every pixel)."""
    solver: str = "daqp"
    """qpsolvers backend (``daqp``, ``quadprog``, ``osqp``, ... any installed one)."""
    slack_weight: float = 1.0e4
    """Quadratic penalty on the relaxation slack when the hard QP is infeasible."""
    tilt_faces: int = 8
    """Faces of the polygonal (inscribed) tilt cone used as the actuator limit in the QP."""
    gravity: float = 9.81
    """Gravitational acceleration [m/s^2] of the acceleration model."""
    thrust_range: tuple[float, float] = (1.0, 30.0)
    """Flyable mass-normalised thrust [m/s^2]; matches the vehicle controller's clamp."""
    max_tilt_deg: float = 50.0
    """Flyable tilt [deg]; matches the vehicle controller's clamp."""
    point_filter: list[float] = field(default_factory=lambda: [0.0, 10.0])
    """Only points at distances in [min, max] metres from the vehicle are considered."""
    memory_steps: int = 50
    """If > 0, each vehicle remembers the obstacle points its constraints used in the last ``memory_steps`` calls
    (world frame) and adds them to the current cloud, so an obstacle that leaves the 87 deg field of view while the
    vehicle passes it still constrains the command for that long. 0: the current image only (the paper). The
    default, 0.5 s at 100 Hz, was chosen on the validation scenes behind the Full policy (docs/shield.md, "Point
    memory"): most of its collisions at 3 m/s were with obstacles beside it, out of view."""
    map_seconds: float = 2.0
    """If > 0, each vehicle also keeps a dense local map of *every* surface its images showed in the last
    ``map_seconds`` [s] (world frame), and its points join the cloud as the point memory's do. Unlike the point
    memory, which keeps only the K points the constraints used, the map keeps an obstacle that was seen but never
    among the tightest, e.g. a box beside a turn. Every ``map_every`` calls the image's points within
    ``map_radius`` are thinned to one point per ``map_voxel`` cube (the newest wins) and merged; points older than
    ``map_seconds`` or farther than ``map_radius`` are dropped. 0: off (the paper; the training-loop shield of
    configs/train/recipe_full.yaml). The default, 2 s at 0.2 m within 6 m, was chosen on benchmark validation behind
    the Full policy: 28 against 77 collisions in 640 flights at level success (docs/shield.md, "Local map")."""
    map_voxel: float = 0.2
    """Edge [m] of the cubes the local map keeps one point of (``map_seconds`` > 0)."""
    map_radius: float = 6.0
    """Points farther than this from the vehicle [m] are neither added to nor kept in the local map."""
    map_every: int = 5
    """The local map takes in the current image every this many calls (5: 20 Hz at 100 Hz)."""
    z_window: list[float] = field(default_factory=lambda: [0.15, 1.0e9])
    """Only points with world height z in [min, max] metres are obstacles for the shield. The default drops the
    ground (floor at z = 0): with the |r|^2 barrier, floor points 2-8 m ahead of a vehicle cruising at 5 m/s and
    1.5 m altitude violate the HOCBF row although the flight is level, so an unfiltered floor keeps the shield on
    and pushes the vehicle up. Altitude is left to the policy (its height reward) as in the paper's training."""
    lag_s: float = 0.15
    """Delay-aware barrier: if > 0, the HOCBF rows constrain the state predicted this long ahead, p + v lag +
    a lag^2 / 2 and v + a lag, with a the vehicle's current acceleration (from its velocity one ``control_dt`` ago,
    as an IMU would give it; 0 on a vehicle's first call or after ``reset``). A command turns into acceleration
    only through the attitude loop and the motors (the vehicle's step response reaches 63 % after 0.16 s,
    docs/shield.md "Lag"); until then the vehicle keeps moving on the acceleration it has, so the rows of a
    lag-free shield act on a state that is gone when the correction arrives. 0: the current state (the paper).
    The default 0.15 s lies between the measured equivalent delay (0.141 s) and the 63 % time (0.16 s)."""
    control_dt: float = 0.01
    """Period of the shield's calls [s] (the vehicle's command period); with ``lag_s`` > 0 the acceleration is
    (v - v_previous_call) / control_dt."""
    min_altitude: float = 0.35
    """If > 0, one more HOCBF row keeps the vehicle's height z (ground at z = 0, known from the state estimate, not
    the camera) above this value [m]: the planar barrier B = z - min_altitude gives a_z >= -alpha1 v_z - alpha0 B.
    Unlike the point barrier it is exact for a plane, so level flight never triggers it. Without it the obstacle
    rows' corrections, or a policy's own dive, can take a vehicle into the unseen ground. 0: off (the paper's
    depth-only shield, and the training-loop shield the shipped Full was trained behind). Default 0.35 since
    2026-11-27, chosen on the benchmark validation scenes (docs/shield.md, "Ground row")."""
    barrier: str = "braking"
    """Which barrier each obstacle point gets. ``braking`` (default): the first-order stopping-distance barrier
    h = sqrt(2 a_b (|r| - r_safe)) - c, with c the closing speed towards the point and a_b = ``brake_accel``: the
    vehicle may approach a point only as fast as braking at a_b still stops it r_safe away (gain ``brake_gain``;
    docs/shield.md, "Braking barrier"). ``distance``: the paper's HOCBF on B = |r|^2 - r_safe^2 (gains ``alpha0``,
    ``alpha1``), whose head-on row allows about p d / 2 of closing speed at distance d whatever the vehicle can
    brake, so that at high speed it asks for more deceleration than the tilt limit gives. ``alpha0``/``alpha1``
    also set the altitude rows with either barrier. ``backup``: h = D - r_safe with D the closest distance to the
    point over one braking maneuver shared by every point, straight along -v at ``brake_accel`` to a stop
    (``backup_rows``; gain ``brake_gain``): a point beside the path that this maneuver clears by r_safe does not slow
    the vehicle, and every point's row holds at once under that maneuver (docs/shield.md, "Backup barrier")."""
    brake_accel: float = 10.0
    """a_b [m/s^2] of the braking barrier: the deceleration it plans with, chosen on the validation scenes
    (docs/shield.md, "Braking barrier"; 8 until 2026-11-26); the tilt limit gives at most g tan(50 deg) =
    11.7 m/s^2 level."""
    brake_gain: float = 4.0
    """Class-K gain [1/s] of the braking barrier's first-order condition hdot >= -gain h (chosen on validation)."""
    passing: bool = False
    """Braking barrier only: also let a point pass when the velocity points outside the collision cone of its
    r_safe ball (the union of the braking barrier and the cone barrier h_c = r.v + |v| sqrt(|r|^2 - r_safe^2),
    each point with the one that gives it more room; same gain). The braking barrier alone brakes for points
    beside the path, which straight flight would pass (docs/shield.md, "It brakes for points beside the path")."""
    along_weight: float = 1.0
    """Cost weight of the correction's component along the horizontal velocity (braking or speeding up) in the QP's
    objective, 1/2 (a - a_raw)^T W (a - a_raw) with W = I + (along_weight - 1) u u^T + (vertical_weight - 1) e3 e3^T
    (u: the horizontal velocity's direction, faded in below 1 m/s). 1 (default): the paper's minimum-norm
    correction. Above 1 the shield prefers to satisfy a row by steering away from the point rather than braking;
    every row holds either way, only which safe command is chosen changes (docs/shield.md, "Correction metric")."""
    vertical_weight: float = 1.0
    """Cost weight of the correction's vertical component in the QP's objective (see ``along_weight``). Above 1 the
    shield prefers horizontal corrections to climbs and dives."""
    max_altitude: float = 0.0
    """If > 0, one more planar HOCBF row keeps z below this value [m] (a geofence ceiling): B = max_altitude - z
    gives -a_z >= alpha1 v_z - alpha0 B. 0: off (the paper). Without it the obstacle rows may resolve a conflict by
    lifting the vehicle over the obstacles, out of the flight volume (docs/shield.md, "Ceiling row")."""

    fence: bool = False
    """If true, the sides of the flight volume (a geofence: the task's out-of-bounds boundary, given to
    :meth:`~shield_nav.safety.shield.HOCBFShield.filter` as ``fence``) are obstacles for the shield: each call adds,
    for every side plane within ``point_filter``'s range, the point of the plane nearest to the vehicle (and to its
    lagged prediction) to the cloud, so the barrier lets the vehicle close on the fence only as fast as it can still
    stop ``r_safe`` short of it, and leaves it free to fly along it. False (default): the paper's shield, which knows
    only what the camera shows (docs/shield.md, "Geofence")."""
    fence_inset: float = 0.0
    """[m] The fence stands this far inside the given boundary (``fence``)."""

    depth_filter: str = "none"
    """Pre-filter of each depth image before the shield turns it into points (the policy always sees the image as
    it comes): ``"none"`` (default; the paper), ``"median_cross"`` (each valid pixel becomes the median of itself and
    its valid 4-neighbours, a window that keeps one-pixel-wide lines) or ``"median_3x3"`` (its 8-neighbours).
    Stereo noise grows as z^2 and the shield's rows follow the *nearest* points of each sector, so per-pixel noise
    pulls the constraints towards the vehicle, and the local map keeps those near outliers for ``map_seconds``
    (docs/shield.md, "Depth noise")."""

    hypotheses: str = "top"
    """Which of a multi-hypothesis policy's candidate commands the shield filters. ``"top"`` (default): the policy's
    own choice, the best-scored candidate, as every policy deploys without a shield. ``"first_clean"``: when the
    best-scored candidate breaks a row (any point's, with the lagged rows and the altitude rows), the next
    candidate in score order that breaks none is flown instead, uncorrected; if none is clean, the best-scored one
    is corrected by the QP as with ``"top"``. ``"safest"``: the same, except that when none is clean the candidate
    with the largest smallest row margin is corrected. The evaluation asks the policy for its candidates only when
    this is not ``"top"`` (docs/shield.md, "Choosing among the policy's hypotheses")."""

    def validate(self, prefix: str = "") -> None:
        """Reject bad values, naming the key."""
        require(self.depth_filter in DEPTH_FILTERS, f"{prefix}depth_filter",
                f"must be one of {list(DEPTH_FILTERS)}, got {self.depth_filter!r}")  # fmt: skip
        require(self.hypotheses in HYPOTHESIS_MODES, f"{prefix}hypotheses",
                f"must be one of {list(HYPOTHESIS_MODES)}, got {self.hypotheses!r}")  # fmt: skip
        require(self.alpha0 > 0, f"{prefix}alpha0", f"must be > 0, got {self.alpha0}")
        require(self.alpha1 > 0, f"{prefix}alpha1", f"must be > 0, got {self.alpha1}")
        require(self.r_safe > 0, f"{prefix}r_safe", f"must be > 0, got {self.r_safe}")
        require(self.max_constraints >= 1, f"{prefix}max_constraints", "must be >= 1")
        require(0 <= self.active_set_iterations <= 50, f"{prefix}active_set_iterations", "must be in [0, 50]")
        require(self.active_set_tol >= 0, f"{prefix}active_set_tol", "must be >= 0")
        require(self.azimuth_sectors >= 1 and self.elevation_sectors >= 1, f"{prefix}azimuth_sectors", "must be >= 1")
        require(self.voxel >= 0, f"{prefix}voxel", "must be >= 0")
        require(
            math.isfinite(self.min_altitude) and self.min_altitude >= 0,
            f"{prefix}min_altitude",
            f"must be finite and >= 0, got {self.min_altitude}",
        )
        require(
            math.isfinite(self.max_altitude) and (self.max_altitude == 0 or self.max_altitude > self.min_altitude),
            f"{prefix}max_altitude",
            f"must be 0 (off) or finite and > min_altitude ({self.min_altitude}), got {self.max_altitude}",
        )
        require(isinstance(self.fence, bool), f"{prefix}fence", f"must be true or false, got {self.fence!r}")
        require(0.0 <= self.fence_inset <= 10.0 and math.isfinite(self.fence_inset), f"{prefix}fence_inset",
                f"must be in [0, 10] m, got {self.fence_inset}")  # fmt: skip
        require(self.barrier in ("distance", "braking", "backup"), f"{prefix}barrier",
                f"must be 'distance', 'braking' or 'backup', got {self.barrier!r}")  # fmt: skip
        require(self.brake_accel > 0 and math.isfinite(self.brake_accel), f"{prefix}brake_accel",
                f"must be > 0, got {self.brake_accel}")  # fmt: skip
        require(self.brake_gain > 0 and math.isfinite(self.brake_gain), f"{prefix}brake_gain",
                f"must be > 0, got {self.brake_gain}")  # fmt: skip
        require(isinstance(self.passing, bool), f"{prefix}passing", f"must be true or false, got {self.passing!r}")
        require(not self.passing or self.barrier == "braking", f"{prefix}passing",
                f"needs barrier 'braking' (it is the braking barrier's union with the collision cone), got barrier "
                f"{self.barrier!r}")  # fmt: skip
        for key in ("along_weight", "vertical_weight"):
            val = getattr(self, key)
            require(math.isfinite(val) and 0.01 <= val <= 1000, f"{prefix}{key}", f"must be in [0.01, 1000], got {val}")
        require(0 <= self.memory_steps <= 1000, f"{prefix}memory_steps", "must be in [0, 1000]")
        require(0.0 <= self.map_seconds <= 60.0 and math.isfinite(self.map_seconds), f"{prefix}map_seconds",
                f"must be in [0, 60] s (0: off), got {self.map_seconds}")  # fmt: skip
        require(0.01 <= self.map_voxel <= 5.0 and math.isfinite(self.map_voxel), f"{prefix}map_voxel",
                f"must be in [0.01, 5] m, got {self.map_voxel}")  # fmt: skip
        require(0.0 < self.map_radius <= 100.0 and math.isfinite(self.map_radius), f"{prefix}map_radius",
                f"must be in (0, 100] m, got {self.map_radius}")  # fmt: skip
        require(isinstance(self.map_every, int) and 1 <= self.map_every <= 1000, f"{prefix}map_every",
                f"must be an integer in [1, 1000], got {self.map_every!r}")  # fmt: skip
        require(0.0 <= self.lag_s <= 1.0 and math.isfinite(self.lag_s), f"{prefix}lag_s",
                f"must be in [0, 1] s, got {self.lag_s}")  # fmt: skip
        require(self.control_dt > 0 and math.isfinite(self.control_dt), f"{prefix}control_dt",
                f"must be > 0, got {self.control_dt}")  # fmt: skip
        require(
            self.solver in qpsolvers.available_solvers,
            f"{prefix}solver",
            f"{self.solver!r} is not an installed qpsolvers backend; installed: {qpsolvers.available_solvers}",
        )
        require(self.slack_weight > 0, f"{prefix}slack_weight", "must be > 0")
        require(self.tilt_faces >= 3, f"{prefix}tilt_faces", "must be >= 3")
        lo, hi = self.thrust_range
        require(0 < lo < hi, f"{prefix}thrust_range", f"must satisfy 0 < min < max, got {self.thrust_range}")
        require(0 < self.max_tilt_deg < 90, f"{prefix}max_tilt_deg", "must be in (0, 90)")
        require(
            len(self.z_window) == 2 and self.z_window[0] < self.z_window[1],
            f"{prefix}z_window",
            f"must be [min, max] with min < max, got {self.z_window}",
        )
        require(
            len(self.point_filter) == 2 and 0 <= self.point_filter[0] < self.point_filter[1],
            f"{prefix}point_filter",
            f"must be [min, max] with 0 <= min < max, got {self.point_filter}",
        )


HYPOTHESIS_MODES = ("top", "first_clean", "safest")
"""Values of :attr:`ShieldConfig.hypotheses`."""
