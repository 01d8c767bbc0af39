"""Vehicle configuration: the airframe, motors, aerodynamics and the PX4-style inner loop.

Every physical parameter carries its unit. Where each default comes from is listed in ``docs/vehicle.md``.
Frames: world is ENU-like (x forward along the course, y left, z up), body is FLU (x forward, y left, z up).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from envs.config import require


@dataclass
class AirframeConfig:
    """Rigid body, geometry and aerodynamics of a ~1 kg, 250-mm-class vision quadrotor."""

    mass: float = 1.0
    """Total mass [kg]."""
    inertia: tuple[float, float, float] = (3.0e-3, 3.0e-3, 5.5e-3)
    """Principal moments of inertia about body x, y, z [kg m^2] (lumped-mass estimate, see docs/vehicle.md)."""
    arm_length: float = 0.125
    """Distance from the centre of mass to each rotor axis [m] (250 mm motor-to-motor diagonal)."""
    collision_radius: float = 0.2
    """Radius of the collision sphere centred on the body origin [m]; covers frame and 5-inch props."""
    linear_drag: tuple[float, float, float] = (0.30, 0.30, 0.10)
    """Rotor-drag coefficients along body x, y, z [1/s]: a_drag_b = -diag(d) v_b (mass-normalised, linear)."""
    quadratic_drag_area: float = 0.012
    """Parasitic drag area C_d * A [m^2]: F = -1/2 rho C_d A |v| v (world frame)."""
    air_density: float = 1.225
    """Air density rho [kg/m^3] (ISA sea level)."""

    def validate(self, prefix: str = "") -> None:
        """Reject non-physical values, naming the key."""
        require(self.mass > 0, f"{prefix}mass", f"must be > 0 kg, got {self.mass}")
        require(all(i > 0 for i in self.inertia), f"{prefix}inertia", f"must be > 0, got {self.inertia}")
        require(self.arm_length > 0, f"{prefix}arm_length", f"must be > 0 m, got {self.arm_length}")
        require(self.collision_radius > 0, f"{prefix}collision_radius", f"must be > 0 m, got {self.collision_radius}")
        require(all(d >= 0 for d in self.linear_drag), f"{prefix}linear_drag", f"must be >= 0, got {self.linear_drag}")
        require(self.quadratic_drag_area >= 0, f"{prefix}quadratic_drag_area", "must be >= 0")
        require(self.air_density >= 0, f"{prefix}air_density", "must be >= 0")


@dataclass
class MotorConfig:
    """Rotor thrust/torque coefficients and first-order, asymmetric rotor-speed dynamics."""

    thrust_to_weight: float = 3.8
    """Total maximum static thrust divided by weight [-]."""
    max_rotor_speed: float = 2600.0
    """Rotor speed at full thrust [rad/s]; with the thrust sets k_f = T_max / w_max^2."""
    min_thrust_fraction: float = 0.02
    """Idle thrust as a fraction of the per-motor maximum [-] (motors never stop in flight)."""
    moment_ratio: float = 0.016
    """Rotor drag-torque to thrust ratio k_m / k_f [m] (PX4 x500 Gazebo model's momentConstant)."""
    time_constant_up: float = 0.0125
    """Rotor-speed time constant when spinning up [s] (PX4 x500 Gazebo model)."""
    time_constant_down: float = 0.025
    """Rotor-speed time constant when spinning down [s] (PX4 x500 Gazebo model)."""

    def validate(self, prefix: str = "") -> None:
        """Reject non-physical values, naming the key."""
        require(self.thrust_to_weight > 1.0, f"{prefix}thrust_to_weight", f"must be > 1, got {self.thrust_to_weight}")
        require(self.max_rotor_speed > 0, f"{prefix}max_rotor_speed", "must be > 0 rad/s")
        require(0.0 <= self.min_thrust_fraction < 0.5, f"{prefix}min_thrust_fraction", "must be in [0, 0.5)")
        require(self.moment_ratio > 0, f"{prefix}moment_ratio", "must be > 0 m")
        require(self.time_constant_up > 0, f"{prefix}time_constant_up", "must be > 0 s")
        require(self.time_constant_down > 0, f"{prefix}time_constant_down", "must be > 0 s")


@dataclass
class ControllerConfig:
    """PX4-style attitude (mc_att_control) and rate (mc_rate_control) loops plus control allocation.

    Gains act on PX4's normalised torque (see docs/vehicle.md for its physical scale on this airframe).
    """

    attitude_p: tuple[float, float, float] = (6.5, 6.5, 2.8)
    """Attitude P gains roll, pitch, yaw [1/s] (PX4 MC_ROLL_P, MC_PITCH_P (older default), MC_YAW_P)."""
    yaw_weight: float = 0.4
    """Yaw de-prioritisation weight in the reduced-attitude controller [-] (PX4 MC_YAW_WEIGHT)."""
    max_rate_deg: tuple[float, float, float] = (220.0, 220.0, 200.0)
    """Body-rate setpoint limits roll, pitch, yaw [deg/s] (PX4 MC_ROLLRATE_MAX, MC_PITCHRATE_MAX, MC_YAWRATE_MAX)."""
    rate_p: tuple[float, float, float] = (0.15, 0.15, 0.2)
    """Rate P gains [normalised torque per rad/s] (PX4 MC_ROLLRATE_P, MC_PITCHRATE_P, MC_YAWRATE_P)."""
    rate_i: tuple[float, float, float] = (0.2, 0.2, 0.1)
    """Rate I gains [normalised torque per rad] (PX4 MC_ROLLRATE_I, MC_PITCHRATE_I, MC_YAWRATE_I)."""
    rate_d: tuple[float, float, float] = (0.003, 0.003, 0.0)
    """Rate D gains on the measured angular acceleration [normalised torque per rad/s^2] (PX4 MC_*RATE_D)."""
    rate_integrator_limit: tuple[float, float, float] = (0.3, 0.3, 0.3)
    """Rate integrator limit [normalised torque] (PX4 MC_RR_INT_LIM etc.)."""
    dgyro_cutoff_hz: float = 30.0
    """Low-pass cutoff of the angular-acceleration estimate used by the D term [Hz] (PX4 IMU_DGYRO_CUTOFF)."""
    airmode: bool = False
    """If true, collective thrust may rise to keep roll/pitch authority at low thrust (PX4 MC_AIRMODE=1)."""
    max_tilt_deg: float = 50.0
    """Commands tilting the thrust axis more than this from vertical are clamped [deg]."""
    thrust_range: tuple[float, float] = (1.0, 30.0)
    """Accepted mass-normalised collective thrust commands [m/s^2]; outside is clamped."""

    def validate(self, prefix: str = "") -> None:
        """Reject inconsistent values, naming the key."""
        require(all(g >= 0 for g in self.attitude_p), f"{prefix}attitude_p", "must be >= 0")
        require(0.0 <= self.yaw_weight <= 1.0, f"{prefix}yaw_weight", f"must be in [0, 1], got {self.yaw_weight}")
        require(all(r > 0 for r in self.max_rate_deg), f"{prefix}max_rate_deg", "must be > 0")
        for name in ("rate_p", "rate_i", "rate_d", "rate_integrator_limit"):
            require(all(g >= 0 for g in getattr(self, name)), f"{prefix}{name}", "must be >= 0")
        require(self.dgyro_cutoff_hz > 0, f"{prefix}dgyro_cutoff_hz", "must be > 0 Hz")
        require(0.0 < self.max_tilt_deg < 90.0, f"{prefix}max_tilt_deg", f"must be in (0, 90), got {self.max_tilt_deg}")
        lo, hi = self.thrust_range
        require(0.0 <= lo < hi, f"{prefix}thrust_range", f"must satisfy 0 <= min < max, got {self.thrust_range}")


@dataclass
class VehicleConfig:
    """Everything that defines the simulated quadrotor and how it is stepped."""

    airframe: AirframeConfig = field(default_factory=AirframeConfig)
    """Rigid body, geometry and drag."""
    motor: MotorConfig = field(default_factory=MotorConfig)
    """Rotors."""
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    """PX4-style inner loop."""
    gravity: float = 9.81
    """Gravitational acceleration [m/s^2]."""
    physics_dt: float = 0.002
    """Physics and inner-loop period [s] (500 Hz)."""
    substeps: int = 5
    """Physics steps per command period; command period = physics_dt * substeps (default 10 ms, 100 Hz)."""

    @property
    def command_dt(self) -> float:
        """Policy/command period [s]."""
        return self.physics_dt * self.substeps

    @property
    def max_motor_thrust(self) -> float:
        """Per-motor maximum thrust T_max [N]."""
        return self.motor.thrust_to_weight * self.airframe.mass * self.gravity / 4.0

    @property
    def hover_thrust(self) -> float:
        """Mass-normalised collective thrust that balances gravity [m/s^2] (equals g)."""
        return self.gravity

    def validate(self, prefix: str = "") -> None:
        """Cross-field checks, naming the key."""
        require(self.gravity > 0, f"{prefix}gravity", "must be > 0")
        require(0 < self.physics_dt <= 0.01, f"{prefix}physics_dt", f"must be in (0, 0.01] s, got {self.physics_dt}")
        require(self.substeps >= 1, f"{prefix}substeps", f"must be >= 1, got {self.substeps}")
        t_max_total = 4.0 * self.max_motor_thrust / self.airframe.mass
        require(
            self.controller.thrust_range[1] <= t_max_total,
            f"{prefix}controller.thrust_range",
            f"max {self.controller.thrust_range[1]} m/s^2 exceeds what the motors give ({t_max_total:.2f} m/s^2)",
        )
