"""Configuration of the navigation task (``ShieldNav-v0``): scenes, episodes, actions, rewards, randomization.

Every field has a docstring with its unit. Load with ``envs.config.load_config(NavConfig, files, overrides)``;
unknown keys and bad values fail at construction with the full dotted key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from envs.camera import CameraConfig, DepthNoiseConfig
from envs.config import require
from envs.vehicle.config import VehicleConfig

REWARD_TERMS = ("navigation", "safety", "smooth", "collision", "success", "speed", "height")
CIRCLE_WINDOW_S = 10.0
"""The window [s] within which a flight's net heading rotation is measured (``episode/circling``, the evaluation's
``metrics.max_turns``)."""
CIRCLE_TURNS = 1.5
"""Net heading rotation [full turns] within :data:`CIRCLE_WINDOW_S` from which a flight counts as circling."""


@dataclass
class SceneSetConfig:
    """Which scenes the envs fly in."""

    family: str = "train"
    """Scene family (train, ablation, benchmark, dynamic, forest)."""
    indices: list[int] = field(default_factory=lambda: list(range(16)))
    """Scene indices within the family; for ``train`` these are the curriculum levels in order."""
    seed: int | None = None
    """Family seed (None: the family's default seed; train and eval seed ranges are disjoint)."""
    field_resolution: float = 0.2
    """Grid spacing of the privileged fields [m]. 0.2 m keeps 16 training scenes at ~16 MB each (0.1 m: ~128 MB)."""
    tile_gap: float = 20.0
    """Gap between scene tiles in the MuJoCo world [m] (each scene is placed at its own x offset)."""


@dataclass
class EpisodeConfig:
    """Starts, goals, target speeds, success and time limits."""

    target_speeds: list[float] = field(default_factory=lambda: [3.0, 5.0, 7.0, 9.0])
    """Target speeds [m/s]: each episode samples one uniformly (or from ``speed_range`` if it is set)."""
    speed_range: list[float] = field(default_factory=list)
    """If [lo, hi] is given, target speeds are sampled uniformly from it instead of ``target_speeds``."""
    goal_anchors: int = 9
    """K > 0: goals are drawn among K anchor points across the goal region, each with its own geodesic field, so
    the navigation reward leads to the episode's goal (see ``envs.fields.anchors``). 0: goals uniform in the goal
    region and Phi flows to the whole region (the paper's literal per-scene map; the final approach to the goal's
    side of the region is then unrewarded). Only used with ``reward.navigation: geodesic``."""
    goal_radius: float = 5.0
    """Success when the vehicle is within this distance of the goal point [m] (paper: 5 m)."""
    yaw_cone_deg: float = 30.0
    """Initial yaw is sampled within +-this of the direction to the goal [deg]."""
    initial_speed_fraction: list[float] = field(default_factory=lambda: [0.0, 0.0])
    """Initial forward speed as a fraction [lo, hi] of the target speed, sampled uniformly."""
    timeout_factor: float = 2.5
    """Time limit = timeout_factor * straight-line distance / target speed + 5 s."""
    deadline: str = "truncate"
    """What the time limit is to the learner. ``truncate`` (default): a time-out is a truncation, bootstrapped from
    the value of the state it stops in, so the return ignores the clock. ``terminate``: the time limit is part of the
    task, as the evaluation counts it (a time-out is a failure): a time-out ends the return (no bootstrap, no success
    bonus), and the privileged critic vector gets two more columns, the time left and the slack
    (:data:`envs.navigation.env.CLOCK_EXTRA`), so that its value can depend on the clock (Pardo et al. 2018, "Time
    Limits in Reinforcement Learning")."""
    clock_input: bool = False
    """Add the observation group ``clock`` (N, 1): the slack, time left x target speed / the straight-line distance
    still to fly to the goal's radius, / 3 and clipped to [0, 1] (1: three times the time the target speed needs;
    below 1/3: late). A policy input a vehicle has onboard (its clock, the goal, the deadline)."""
    out_of_bounds_margin: float = 3.0
    """The episode ends when the vehicle leaves the scene bounds by more than this in x or y [m] (starts are at
    the x = 0 edge, so a smaller margin ends exploratory episodes that drift backwards almost at once)."""


@dataclass
class ActionConfig:
    """How the policy's normalised action in [-1, 1]^4 maps to the vehicle command [f_n, phi, theta, psi]."""

    thrust_min: float = 2.0
    """f_n at action -1 [m/s^2]; action 0 is hover (g); piecewise linear in between."""
    thrust_max: float = 25.0
    """f_n at action +1 [m/s^2]."""
    max_tilt_deg: float = 45.0
    """Roll and pitch references at action +-1 [deg]."""
    yaw_range_deg: float = 60.0
    """Yaw reference relative to the yaw base (``yaw_base``) at action +-1 [deg] (a heading lead, rate-like)."""
    yaw_base: str = "heading"
    """What the yaw action leads: ``heading`` (default: the current heading, so action 0 holds it) or ``velocity``
    (the heading of the horizontal velocity, so action 0 turns the camera towards the direction of travel; below
    ``yaw_base_speed`` it blends linearly back to the current heading, which is the base at hover)."""
    yaw_base_speed: float = 1.0
    """With ``yaw_base: velocity``: horizontal speed [m/s] from which the base is the velocity's heading alone."""


@dataclass
class RewardConfig:
    """The paper's seven reward terms. r = sum_i scales[i] * r_i; each r_i is logged as reward/<name>."""

    scales: dict[str, float] = field(
        default_factory=lambda: {
            "navigation": 1.0,
            "safety": 0.05,
            "smooth": 0.002,
            "collision": 10.0,
            "success": 10.0,
            "speed": 0.02,
            "height": 0.1,
        }
    )
    """alpha_i per term (names: navigation, safety, smooth, collision, success, speed, height)."""
    navigation: str = "geodesic"
    """Potential Phi of the navigation term: ``geodesic`` (Dijkstra field) or ``euclidean`` (distance to goal)."""
    nav_lambda: float = 1.0
    """lambda: reward per metre of progress along Phi [1/m]."""
    nav_clamp: float = 0.2
    """C: progress per step is clamped to [-C, C] [m]."""
    cbf_gamma: float = 2.0
    """gamma of the CBF safety term [1/s]."""
    cbf_d_safe: float = 0.6
    """d_safe of the barrier b = d(x) - d_safe [m] (d: ESDF at the vehicle centre)."""
    cbf_delta_min: float = -2.0
    """delta_min: lower clip of the safety term (paper: -2)."""
    smooth_magnitude: float = 0.1
    """Weight of |a|^2 inside the smoothness term (the action change |a - a_prev|^2 has weight 1)."""
    height_band: list[float] = field(default_factory=lambda: [0.5, 2.5])
    """Altitudes [lo, hi] outside which the height term penalises linearly [m]."""


@dataclass
class CurriculumConfig:
    """legged_gym-style level curriculum over the scene list (levels = scene indices in order)."""

    enabled: bool = True
    """Move envs between scenes by outcome; when off, scenes are sampled uniformly per episode."""
    initial_max_level: int = 3
    """Initial levels are sampled uniformly in [0, initial_max_level]."""
    demote_after: int = 2
    """Consecutive failures that move an env down one level."""


@dataclass
class Range:
    """A uniform range [lo, hi]; ``enabled`` false means the nominal value is used."""

    enabled: bool = False
    """Sample this parameter per episode."""
    lo: float = 1.0
    """Lower bound (a scale factor unless the field says otherwise)."""
    hi: float = 1.0
    """Upper bound."""

    def validate(self, prefix: str = "") -> None:
        """Lo <= hi."""
        require(self.lo <= self.hi, f"{prefix}lo", f"must be <= hi ({self.hi}), got {self.lo}")


@dataclass
class RandomizationConfig:
    """Domain randomization, re-sampled per episode for the envs that reset. Every item can be switched off."""

    PRE_FIELD_VALUES: ClassVar[dict[str, Any]] = {"command_latency": False}
    """A stored config from before ``command_latency`` flew given commands without the latency (``stored_config``)."""

    mass_scale: Range = field(default_factory=lambda: Range(True, 0.9, 1.1))
    """Plant mass scale (the controller keeps the nominal mass)."""
    inertia_scale: Range = field(default_factory=lambda: Range(True, 0.85, 1.15))
    """Plant inertia scale."""
    thrust_scale: Range = field(default_factory=lambda: Range(True, 0.9, 1.1))
    """Motor maximum-thrust (thrust coefficient) scale."""
    torque_scale: Range = field(default_factory=lambda: Range(True, 0.85, 1.15))
    """Rotor drag-torque coefficient scale."""
    motor_tau_scale: Range = field(default_factory=lambda: Range(True, 0.8, 1.25))
    """Motor time-constant scale (up and down together)."""
    gain_scale: Range = field(default_factory=lambda: Range(True, 0.85, 1.15))
    """Inner-loop gain scale (attitude P and rate P/I/D together)."""
    action_latency_steps: list[int] = field(default_factory=lambda: [0, 2])
    """Action latency, whole policy steps [lo, hi], sampled per episode."""
    command_latency: bool = True
    """The action latency also delays the commands given to ``step(actions, commands=...)`` (the shield's output, a
    baseline's commands), as it delays the policy's actions; the previous-action observation is then the delayed
    command's normalised equivalent. False: such commands are flown at once, whatever the latency (the behaviour until
    2026-12-05, which the shipped Full was trained with; ``configs/train/recipe_full.yaml`` keeps it)."""
    vel_noise_std: float = 0.05
    """Std of Gaussian noise on the observed body velocity [m/s]."""
    att_noise_std_deg: float = 0.5
    """Std of a random small rotation applied to the observed attitude [deg]."""
    wind_max: float = 1.0
    """Constant wind force magnitude per episode, uniform in [0, wind_max], horizontal direction uniform [N]."""
    gust_std: float = 0.3
    """Std of the gust force (an Ornstein-Uhlenbeck process, 1 s correlation) [N]."""
    depth_noise: DepthNoiseConfig = field(
        default_factory=lambda: DepthNoiseConfig(depth_sigma_coeff=0.01, dropout_prob=0.02, holes_per_frame=0.5)
    )
    """Depth sensor model (policy image only; the critic never sees it)."""

    def validate(self, prefix: str = "") -> None:
        """Check ranges."""
        lo, hi = self.action_latency_steps
        require(0 <= lo <= hi <= 10, f"{prefix}action_latency_steps", f"must be 0 <= lo <= hi <= 10, got {[lo, hi]}")
        require(self.vel_noise_std >= 0, f"{prefix}vel_noise_std", "must be >= 0")
        require(self.att_noise_std_deg >= 0, f"{prefix}att_noise_std_deg", "must be >= 0")
        require(self.wind_max >= 0, f"{prefix}wind_max", "must be >= 0")
        require(self.gust_std >= 0, f"{prefix}gust_std", "must be >= 0")

    def disable(self) -> None:
        """Switch every randomization off (evaluation without randomization)."""
        for name in ("mass_scale", "inertia_scale", "thrust_scale", "torque_scale", "motor_tau_scale", "gain_scale"):
            getattr(self, name).enabled = False
        self.action_latency_steps = [0, 0]
        self.vel_noise_std = self.att_noise_std_deg = self.wind_max = self.gust_std = 0.0
        self.depth_noise = DepthNoiseConfig()


@dataclass
class LocalMapConfig:
    """The privileged local map of the teacher observation: the ESDF sampled on a grid around the vehicle.

    Grid points are ``pos + Rz(psi) [x, y, 0] + [0, 0, z]`` for every (x, y, z) in ``xs`` x ``ys`` x ``zs`` (the
    heading frame: x forward, y left, level). Each value is ``clip(esdf, -clip, clip) / clip``. The map sees through
    walls and has no noise: it is privileged information for a teacher (``info["teacher"]``), never the student.
    """

    enabled: bool = False
    """Compute ``info["teacher"]`` (the clean state followed by the local map) every step."""
    xs: list[float] = field(default_factory=lambda: [-1.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.5, 8.0])
    """Forward offsets [m]."""
    ys: list[float] = field(default_factory=lambda: [-4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0])
    """Lateral offsets (left positive) [m]."""
    zs: list[float] = field(default_factory=lambda: [-0.6, 0.0, 0.6])
    """Vertical offsets [m]."""
    clip: float = 3.0
    """ESDF values are clipped to [-clip, clip] and divided by clip [m]."""


@dataclass
class SceneMemoryConfig:
    """An onboard memory of the scene, built only from the policy's own depth frames and pose (observation ``memory``).

    A frame is stored at most every ``interval`` control steps: for each sampled image column, the nearest sampled
    pixel whose world point lies within ``band`` of the vehicle's height (one point per column, its horizontal
    position kept). Each env keeps its last ``frames`` stored frames (0.01 s control steps: 30 x 5 = 1.5 s). Each
    step they are read as ``bins`` equal sectors of bearing in the heading frame (sector
    ``k`` covers ``[-180 + k * 360 / bins, -180 + (k + 1) * 360 / bins)`` deg, 0 = ahead, positive to the left): the
    nearest remembered horizontal distance in each, divided by ``range`` and clipped to 1 (1: nothing within
    ``range``). Unlike the camera it covers beside and behind the vehicle; unlike ``local_map`` it is not privileged:
    it holds what the sensor showed, noise included, placed with the vehicle's pose (odometry without drift).
    """

    enabled: bool = False
    """Compute the ``memory`` observation group (N, bins); list it in the actor's observation set to use it."""
    bins: int = 16
    """Bearing sectors around the vehicle."""
    range: float = 5.0
    """Distances are divided by this and clipped to 1 [m]."""
    frames: int = 30
    """Stored frames remembered per env."""
    interval: int = 5
    """Control steps between stored frames (at least)."""
    band: float = 0.5
    """Half-height of the slab around the vehicle whose points are kept [m]."""
    pixel_stride: int = 4
    """Every ``pixel_stride``-th row and column of the image is sampled."""


@dataclass
class NavConfig:
    """The whole task. See docs/task.md for the MDP in one page."""

    num_envs: int = 64
    """Number of vehicles stepped together."""
    seed: int = 0
    """Seed of the env's random generator (starts, goals, speeds, randomization)."""
    scenes: SceneSetConfig = field(default_factory=SceneSetConfig)
    """Scene set."""
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)
    """Episodes."""
    action: ActionConfig = field(default_factory=ActionConfig)
    """Action scaling."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Rewards."""
    collision_margin: float = 0.0
    """Extra margin [m]: the episode also ends as a collision when the ESDF at the vehicle centre drops below
    vehicle radius + margin. 0: only physical MuJoCo contact counts. The paper's geometric-inflation baseline uses
    0.2 (a doubled 0.4 m margin)."""
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    """Curriculum over the scene list."""
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    """Domain randomization."""
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    """The quadrotor and its inner loop."""
    camera: CameraConfig = field(default_factory=CameraConfig)
    """The depth camera."""
    autoreset: bool = True
    """Reset finished envs inside ``step`` (same-step autoreset). False: finished envs hover, frozen, until reset."""
    critic_depth_pool: list[int] = field(default_factory=lambda: [6, 10])
    """The critic sees the clean depth min-pooled to this (rows, cols) grid."""
    render_depth: bool = True
    """Render the depth camera and apply the sensor model. False (privileged-teacher training): the depth group
    is all zeros, the critic's pooled depth is constant, and the step costs about half as much."""
    local_map: LocalMapConfig = field(default_factory=LocalMapConfig)
    """Privileged local ESDF map for a teacher policy (``info["teacher"]``)."""
    scene_memory: SceneMemoryConfig = field(default_factory=SceneMemoryConfig)
    """Onboard memory of the scene for the policy (observation group ``memory``); off by default."""

    def validate(self, prefix: str = "") -> None:
        """Cross-field checks naming the key."""
        require(self.num_envs >= 1, f"{prefix}num_envs", f"must be >= 1, got {self.num_envs}")
        for k in self.reward.scales:
            require(k in REWARD_TERMS, f"{prefix}reward.scales.{k}", f"unknown reward term; known: {REWARD_TERMS}")
        require(
            self.reward.navigation in ("geodesic", "euclidean"),
            f"{prefix}reward.navigation",
            f"must be 'geodesic' or 'euclidean', got {self.reward.navigation!r}",
        )
        require(self.reward.nav_clamp > 0, f"{prefix}reward.nav_clamp", "must be > 0")
        require(self.reward.cbf_delta_min < 0, f"{prefix}reward.cbf_delta_min", "must be < 0")
        require(len(self.reward.height_band) == 2, f"{prefix}reward.height_band", "must be [lo, hi]")
        require(len(self.scenes.indices) >= 1, f"{prefix}scenes.indices", "must name at least one scene")
        require(self.scenes.field_resolution > 0, f"{prefix}scenes.field_resolution", "must be > 0")
        sp = self.episode.speed_range
        require(
            (len(sp) == 0 and len(self.episode.target_speeds) >= 1 and min(self.episode.target_speeds) > 0)
            or (len(sp) == 2 and 0 < sp[0] <= sp[1]),
            f"{prefix}episode.speed_range",
            "give target_speeds (all > 0) or speed_range [lo, hi] with 0 < lo <= hi",
        )
        require(self.episode.goal_radius > 0, f"{prefix}episode.goal_radius", "must be > 0")
        require(self.episode.goal_anchors >= 0, f"{prefix}episode.goal_anchors", "must be >= 0")
        require(self.episode.deadline in ("truncate", "terminate"), f"{prefix}episode.deadline",
                f"must be 'truncate' or 'terminate', got {self.episode.deadline!r}")  # fmt: skip
        a = self.action
        require(
            0 < a.thrust_min < self.vehicle.gravity < a.thrust_max <= self.vehicle.controller.thrust_range[1],
            f"{prefix}action.thrust_max",
            f"need 0 < thrust_min < g < thrust_max <= vehicle.controller.thrust_range[1]; got {a.thrust_min}, "
            f"{a.thrust_max}",
        )
        require(0 < a.max_tilt_deg <= self.vehicle.controller.max_tilt_deg, f"{prefix}action.max_tilt_deg",
                "must be in (0, vehicle.controller.max_tilt_deg]")  # fmt: skip
        require(a.yaw_base in ("heading", "velocity"), f"{prefix}action.yaw_base",
                f"must be 'heading' or 'velocity', got {a.yaw_base!r}")  # fmt: skip
        require(math.isfinite(a.yaw_base_speed) and a.yaw_base_speed > 0, f"{prefix}action.yaw_base_speed",
                f"must be > 0, got {a.yaw_base_speed}")  # fmt: skip
        require(self.collision_margin >= 0, f"{prefix}collision_margin", "must be >= 0")
        require(len(self.critic_depth_pool) == 2, f"{prefix}critic_depth_pool", "must be [rows, cols]")
        lm = self.local_map
        for k in ("xs", "ys", "zs"):
            require(len(getattr(lm, k)) >= 1, f"{prefix}local_map.{k}", "must hold at least one offset")
        require(lm.clip > 0, f"{prefix}local_map.clip", "must be > 0")
        sm = self.scene_memory
        require(sm.bins >= 1, f"{prefix}scene_memory.bins", f"must be >= 1, got {sm.bins}")
        require(math.isfinite(sm.range) and sm.range > 0, f"{prefix}scene_memory.range", f"must be > 0, got {sm.range}")
        require(sm.frames >= 1, f"{prefix}scene_memory.frames", f"must be >= 1, got {sm.frames}")
        require(sm.interval >= 1, f"{prefix}scene_memory.interval", f"must be >= 1, got {sm.interval}")
        require(math.isfinite(sm.band) and sm.band > 0, f"{prefix}scene_memory.band", f"must be > 0, got {sm.band}")
        require(sm.pixel_stride >= 1, f"{prefix}scene_memory.pixel_stride", f"must be >= 1, got {sm.pixel_stride}")
