"""N quadrotors in one MuJoCo model, stepped together for one command period.

Design (measured in docs/vehicle.md): all N vehicles are free bodies of a single ``MjModel``; their collision
bits let them hit obstacles but never each other, so one ``mj_step`` advances every vehicle and MuJoCo does the
rigid-body integration and contact detection. The inner loop and the motors run in numpy on (N, ...) arrays at
the physics rate; rotor forces, reaction torques, drag and external (wind) forces reach MuJoCo through
``xfrc_applied`` as one world-frame wrench per vehicle at its centre of mass, which is exactly equivalent to the
four rotor point forces plus their drag torques.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from envs.mjcf import VEHICLE_CONAFFINITY, VEHICLE_CONTYPE, VEHICLE_GROUP, fmt
from envs.vehicle.config import VehicleConfig
from envs.vehicle.px4 import MOTOR_SPIN, Allocator, AttitudeRateController, attitude_setpoint, motor_positions
from envs.vehicle.rotations import quat_to_rot


def vehicle_body_xml(index: int, cfg: VehicleConfig, pos: tuple[float, float, float]) -> str:
    """MJCF ``<body>`` for vehicle ``index``: a free joint, explicit inertia, a collision sphere, visual parts."""
    a = cfg.airframe
    name = f"quad_{index}"
    parts = [
        f'<body name="{name}" pos="{fmt(pos)}">',
        f'<freejoint name="{name}"/>',
        f'<inertial pos="0 0 0" mass="{fmt(a.mass)}" diaginertia="{fmt(a.inertia)}"/>',
        # Collision: one sphere (invisible); hits obstacles only (see envs/mjcf.py).
        f'<geom name="{name}_collision" type="sphere" size="{fmt(a.collision_radius)}" '
        f'contype="{VEHICLE_CONTYPE}" conaffinity="{VEHICLE_CONAFFINITY}" group="{VEHICLE_GROUP}" rgba="0 0 0 0"/>',
        # Visual only (no contacts, no mass): body, arms, rotor discs.
        '<geom type="box" size="0.06 0.04 0.02" contype="0" conaffinity="0" group="3" mass="0" '
        'rgba="0.15 0.15 0.2 1"/>',
    ]
    for i, p in enumerate(motor_positions(a.arm_length)):
        colour = "0.9 0.3 0.2 0.6" if i in (0, 2) else "0.2 0.2 0.2 0.6"  # front rotors red
        parts.append(
            f'<geom type="capsule" fromto="0 0 0 {fmt(p)}" size="0.008" contype="0" conaffinity="0" group="3" '
            'mass="0" rgba="0.2 0.2 0.2 1"/>'
        )
        parts.append(
            f'<geom type="cylinder" pos="{fmt(p + np.array([0.0, 0.0, 0.02]))}" size="0.0635 0.002" contype="0" '
            f'conaffinity="0" group="3" mass="0" rgba="{colour}"/>'
        )
    parts.append("</body>")
    return "".join(parts)


def build_model_xml(num: int, cfg: VehicleConfig, world_xml: str = "", spacing: float = 2.0) -> str:
    """The full MJCF: options, N vehicles (first, so their joints lead ``qpos``), then ``world_xml``."""
    cols = max(1, int(math.ceil(math.sqrt(num))))
    bodies = "".join(vehicle_body_xml(i, cfg, (spacing * (i % cols), spacing * (i // cols), 1.0)) for i in range(num))
    return (
        '<mujoco model="shield_nav">'
        '<compiler angle="radian" autolimits="true"/>'
        f'<option timestep="{fmt(cfg.physics_dt)}" gravity="0 0 {fmt(-cfg.gravity)}" integrator="Euler" '
        'density="0" viscosity="0"/>'
        '<visual><global offwidth="640" offheight="480"/><quality shadowsize="2048"/></visual>'
        "<worldbody>"
        '<light pos="0 0 20" dir="0 0 -1" directional="true"/>'
        f"{bodies}{world_xml}"
        "</worldbody></mujoco>"
    )


class Vehicles:
    """N quadrotors with PX4-style inner loops, stepped for one 10 ms command period at a time.

    Command (per vehicle, shape (N, 4)): ``[f_n, phi_ref, theta_ref, psi_ref]``

    =====  ================================================  =========
    index  meaning                                           unit
    =====  ================================================  =========
    0      mass-normalised collective thrust f_n             m/s^2
    1      roll reference phi (ZYX Euler)                    rad
    2      pitch reference theta (ZYX Euler)                 rad
    3      yaw reference psi (absolute, world frame)         rad
    =====  ================================================  =========

    Out-of-range commands are clamped (thrust to ``controller.thrust_range``, tilt to ``controller.max_tilt_deg``);
    a non-finite command raises ``ValueError`` naming the vehicle indices. The controller converts f_n to thrust
    with the *nominal* mass, so a randomised plant mass shows up as a thrust error, as on a real vehicle.

    State views (all (N, ...), world frame ``_w`` or body frame ``_b``): ``pos_w``, ``quat_wb``, ``vel_w``,
    ``ang_vel_b``; derived: ``R_wb``, ``vel_b``. Plant parameters that domain randomisation may change per
    vehicle: ``motor_t_max``, ``motor_tau_up``, ``motor_tau_down``, ``moment_ratio``, ``linear_drag``,
    ``ext_force_w`` and, through :meth:`set_mass_inertia`, mass and inertia; controller gains live in
    ``controller`` as (N, 3) arrays.

    Args:
        num: number of vehicles N.
        cfg: vehicle configuration (defaults if None).
        world_xml: MJCF fragment for the worldbody (scene geoms, mocap bodies). It must not add joints.
    """

    def __init__(self, num: int, cfg: VehicleConfig | None = None, world_xml: str = "") -> None:  # noqa: D107
        if num < 1:
            raise ValueError(f"num must be >= 1, got {num}")
        self.num = num
        self.cfg = cfg = cfg if cfg is not None else VehicleConfig()
        self.model = mujoco.MjModel.from_xml_string(build_model_xml(num, cfg, world_xml))
        self.data = mujoco.MjData(self.model)
        if self.model.nq < 7 * num:
            raise ValueError("world_xml removed vehicle joints")
        if self.model.nq != 7 * num:
            raise ValueError("world_xml must not add joints: vehicles must own every qpos entry")
        self.body_ids = np.array([self.model.body(f"quad_{i}").id for i in range(num)])
        self.geom_ids = np.array([self.model.geom(f"quad_{i}_collision").id for i in range(num)])
        if not np.array_equal(self.body_ids, self.body_ids[0] + np.arange(num)):
            raise RuntimeError("vehicle bodies are expected to be contiguous")
        # Views into MuJoCo's buffers (no copies): writes go straight to the simulator.
        self._qpos = self.data.qpos.reshape(num, 7)
        self._qvel = self.data.qvel.reshape(num, 6)
        self._xfrc = self.data.xfrc_applied[self.body_ids[0] : self.body_ids[0] + num]
        self._geom_to_vehicle = np.full(self.model.ngeom, -1, dtype=np.int64)
        self._geom_to_vehicle[self.geom_ids] = np.arange(num)

        dt = cfg.physics_dt
        self.controller = AttitudeRateController(num, cfg.controller, dt)
        self.allocator = Allocator(cfg)
        self.nominal_mass = cfg.airframe.mass
        # Plant parameters, per vehicle (domain randomisation writes these).
        ones = np.ones(num)
        self.motor_t_max = ones * cfg.max_motor_thrust
        self.motor_tau_up = ones * cfg.motor.time_constant_up
        self.motor_tau_down = ones * cfg.motor.time_constant_down
        self.moment_ratio = ones * cfg.motor.moment_ratio
        self.linear_drag = np.tile(np.array(cfg.airframe.linear_drag, dtype=float), (num, 1))
        self.quadratic_drag = ones * 0.5 * cfg.airframe.air_density * cfg.airframe.quadratic_drag_area
        self.ext_force_w = np.zeros((num, 3))
        self._motor_pos = motor_positions(cfg.airframe.arm_length)  # (4, 3)
        # Buffers.
        self.rotor_speed_buf = np.zeros((num, 4))
        self.motor_thrust_buf = np.zeros((num, 4))
        self.motor_cmd_buf = np.zeros((num, 4))
        self.command_buf = np.zeros((num, 4))
        self.collided_buf = np.zeros(num, dtype=bool)
        self.time = 0.0
        self.reset(np.arange(num), self._qpos[:, :3].copy())

    # ------------------------------------------------------------------ state
    @property
    def pos_w(self) -> np.ndarray:
        """Positions (N, 3) [m], a view."""
        return self._qpos[:, 0:3]

    @property
    def quat_wb(self) -> np.ndarray:
        """Attitude quaternions body-to-world (N, 4) (w, x, y, z), a view."""
        return self._qpos[:, 3:7]

    @property
    def vel_w(self) -> np.ndarray:
        """Linear velocities in the world frame (N, 3) [m/s], a view."""
        return self._qvel[:, 0:3]

    @property
    def ang_vel_b(self) -> np.ndarray:
        """Body rates in the body frame (N, 3) [rad/s], a view (MuJoCo's free-joint convention)."""
        return self._qvel[:, 3:6]

    @property
    def R_wb(self) -> np.ndarray:  # noqa: N802
        """Rotation matrices body-to-world (N, 3, 3)."""
        return quat_to_rot(self.quat_wb)

    @property
    def vel_b(self) -> np.ndarray:
        """Linear velocities in the body frame (N, 3) [m/s]."""
        return np.einsum("nji,nj->ni", self.R_wb, self.vel_w)

    @property
    def k_f(self) -> np.ndarray:
        """Per-vehicle rotor thrust coefficient T = k_f w^2 (N,) [N s^2/rad^2]."""
        return self.motor_t_max / self.cfg.motor.max_rotor_speed**2

    # ------------------------------------------------------------------ set-up
    def set_mass_inertia(self, env_ids: np.ndarray, mass: np.ndarray, inertia: np.ndarray) -> None:
        """Set the plant's mass (M,) [kg] and principal inertia (M, 3) [kg m^2] of ``env_ids``."""
        self.model.body_mass[self.body_ids[env_ids]] = mass
        self.model.body_inertia[self.body_ids[env_ids]] = inertia

    def reset(
        self,
        env_ids: np.ndarray,
        pos_w: np.ndarray,
        quat_wb: np.ndarray | None = None,
        vel_w: np.ndarray | None = None,
        ang_vel_b: np.ndarray | None = None,
    ) -> None:
        """Place vehicles ``env_ids`` (M,) at ``pos_w`` (M, 3), attitude ``quat_wb`` (M, 4, default level).

        Velocities default to zero, rotors spin at the plant's hover speed, controller state is cleared, and the
        collision flag is lowered. Other vehicles are untouched.
        """
        env_ids = np.asarray(env_ids, dtype=np.int64)
        m = len(env_ids)
        self._qpos[env_ids, 0:3] = pos_w
        self._qpos[env_ids, 3:7] = np.array([1.0, 0.0, 0.0, 0.0]) if quat_wb is None else quat_wb
        self._qvel[env_ids, 0:3] = 0.0 if vel_w is None else vel_w
        self._qvel[env_ids, 3:6] = 0.0 if ang_vel_b is None else ang_vel_b
        mass = self.model.body_mass[self.body_ids[env_ids]]
        hover_w = np.sqrt(mass * self.cfg.gravity / 4.0 / self.k_f[env_ids])
        self.rotor_speed_buf[env_ids] = hover_w[:, None]
        self.motor_thrust_buf[env_ids] = (self.k_f[env_ids] * hover_w**2)[:, None]
        self.controller.reset(env_ids, self._qvel[env_ids, 3:6])
        self.command_buf[env_ids] = np.array([self.cfg.gravity, 0.0, 0.0, 0.0])
        self.collided_buf[env_ids] = False
        self._xfrc[env_ids] = 0.0
        if m:
            mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ stepping
    def step(self, command: np.ndarray) -> np.ndarray:
        """Advance all vehicles by one command period (``substeps`` physics steps) under ``command`` (N, 4).

        Returns:
            A (N,) bool array, True for vehicles that touched an obstacle during this period.
        """
        cmd = np.asarray(command, dtype=np.float64)
        if cmd.shape != (self.num, 4):
            raise ValueError(f"command must have shape ({self.num}, 4), got {cmd.shape}")
        bad = ~np.isfinite(cmd).all(axis=1)
        if bad.any():
            raise ValueError(f"non-finite command for vehicle index(es) {np.flatnonzero(bad).tolist()}: {cmd[bad]}")
        f_n, q_sp = attitude_setpoint(cmd, self.cfg.controller)
        self.command_buf[:, 0] = f_n
        self.command_buf[:, 1:] = cmd[:, 1:]
        thrust = f_n * self.nominal_mass  # collective thrust set-point [N] from the nominal mass
        collided = np.zeros(self.num, dtype=bool)
        for _ in range(self.cfg.substeps):
            self._inner_loop(thrust, q_sp)
            mujoco.mj_step(self.model, self.data)
            if self.data.ncon:
                collided |= self._contacts()
        self.time += self.cfg.command_dt
        self.collided_buf |= collided
        return collided

    def _inner_loop(self, thrust: np.ndarray, q_sp: np.ndarray) -> None:
        """One physics-rate pass: attitude -> rates -> allocation -> motors -> wrench into ``xfrc_applied``."""
        ctrl = self.controller
        quat = self.quat_wb
        rate_sp = ctrl.attitude(quat, q_sp)
        torque_n = ctrl.rate(rate_sp, self.ang_vel_b)
        u, ctrl.sat_pos_buf, ctrl.sat_neg_buf = self.allocator.allocate(thrust, torque_n)
        self.motor_cmd_buf[:] = u
        self._motors(u)
        t = self.motor_thrust_buf  # (N, 4) [N]
        p = self._motor_pos
        # Body wrench of four point forces (0, 0, T_i) at r_i plus rotor drag torques -s_i k T_i about z.
        torque_b = np.stack((t @ p[:, 1], -(t @ p[:, 0]), -(t @ MOTOR_SPIN) * self.moment_ratio), axis=1)
        r = quat_to_rot(quat)
        v = self.vel_w
        # Rotor drag, linear in the body frame: F = -m R diag(d) R^T v.  Parasitic drag: F = -1/2 rho CdA |v| v.
        v_b = np.einsum("nji,nj->ni", r, v)
        mass = self.model.body_mass[self.body_ids]
        drag_w = -np.einsum("nij,nj->ni", r, self.linear_drag * v_b) * mass[:, None]
        drag_w -= (self.quadratic_drag * np.linalg.norm(v, axis=1))[:, None] * v
        self._xfrc[:, 0:3] = r[:, :, 2] * t.sum(axis=1, keepdims=True) + drag_w + self.ext_force_w
        self._xfrc[:, 3:6] = np.einsum("nij,nj->ni", r, torque_b)

    def _motors(self, u: np.ndarray) -> None:
        """First-order rotor-speed dynamics with separate spin-up/spin-down time constants, exact per step.

        w_cmd = sqrt(u T_max / k_f);  w <- w_cmd + (w - w_cmd) exp(-dt / tau),  tau = tau_up if w_cmd > w else tau_down.
        Thrust T = k_f w^2 (so a thrust step reaches 63% of its rotor-speed change in tau).
        """
        k_f = self.k_f[:, None]
        w_cmd = np.sqrt(u * self.motor_t_max[:, None] / k_f)
        w = self.rotor_speed_buf
        tau = np.where(w_cmd > w, self.motor_tau_up[:, None], self.motor_tau_down[:, None])
        w = w_cmd + (w - w_cmd) * np.exp(-self.cfg.physics_dt / tau)
        self.rotor_speed_buf[:] = w
        self.motor_thrust_buf[:] = k_f * w * w

    def _contacts(self) -> np.ndarray:
        """(N,) bool: vehicles whose collision geom is in MuJoCo's current contact list."""
        out = np.zeros(self.num, dtype=bool)
        geoms = self.data.contact.geom[: self.data.ncon].reshape(-1)
        veh = self._geom_to_vehicle[geoms]
        out[veh[veh >= 0]] = True
        return out
