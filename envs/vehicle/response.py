"""Closed-loop response experiments on the vehicle: used by tests, the demo and docs/vehicle.md.

Each function flies a fresh :class:`Vehicles` batch open-loop on a fixed command and returns measured figures,
so the same numbers appear in the test assertions, the README demo and the docs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from envs.vehicle.config import VehicleConfig
from envs.vehicle.rotations import rot_to_euler_zyx, wrap_pi
from envs.vehicle.vehicles import Vehicles


@dataclass
class StepResponse:
    """Figures of a step response. Times in s, angles in deg."""

    target: float
    rise_time: float
    """10 % -> 90 % rise time [s]."""
    overshoot_pct: float
    """Peak overshoot in percent of the step."""
    settling_time: float
    """Time after which the response stays within 2 % of the step [s]."""
    final: float
    """Value at the end of the run."""
    max_cross_axis: float
    """Largest excursion on the two other axes [deg] (coupling)."""
    t: np.ndarray
    y: np.ndarray


def _figures(t: np.ndarray, y: np.ndarray, target: float, cross: np.ndarray) -> StepResponse:
    frac = y / target
    t10 = t[np.argmax(frac >= 0.1)] if np.any(frac >= 0.1) else math.inf
    t90 = t[np.argmax(frac >= 0.9)] if np.any(frac >= 0.9) else math.inf
    outside = np.flatnonzero(np.abs(y - target) > 0.02 * abs(target))
    settle = 0.0 if len(outside) == 0 else (t[outside[-1] + 1] if outside[-1] + 1 < len(t) else math.inf)
    return StepResponse(
        target=target,
        rise_time=float(t90 - t10),
        overshoot_pct=float(max(0.0, (np.max(frac) - 1.0) * 100.0)),
        settling_time=float(settle),
        final=float(y[-1]),
        max_cross_axis=float(np.max(np.abs(cross))),
        t=t,
        y=y,
    )


def attitude_step(
    axis: str, amplitude_deg: float, duration: float = 1.5, cfg: VehicleConfig | None = None
) -> StepResponse:
    """Hover, then step one attitude reference (``roll``, ``pitch`` or ``yaw``) by ``amplitude_deg``.

    For roll/pitch the collective thrust is g / cos(tilt), the level-flight thrust, so altitude is held.
    """
    cfg = cfg or VehicleConfig()
    idx = {"roll": 0, "pitch": 1, "yaw": 2}[axis]
    veh = Vehicles(1, cfg)
    amp = math.radians(amplitude_deg)
    cmd = np.zeros((1, 4))
    cmd[0, 1 + idx] = amp
    cmd[0, 0] = cfg.gravity / (math.cos(amp) if idx < 2 else 1.0)
    steps = int(round(duration / cfg.command_dt))
    t = np.arange(1, steps + 1) * cfg.command_dt
    euler = np.empty((steps, 3))
    for k in range(steps):
        veh.step(cmd)
        euler[k] = rot_to_euler_zyx(veh.R_wb)[0]
    euler[:, 2] = wrap_pi(euler[:, 2])
    deg = np.degrees(euler)
    cross = np.delete(deg, idx, axis=1)
    return _figures(t, deg[:, idx], amplitude_deg, cross)


def hover_hold(duration: float = 5.0, kick_rate: float = 0.5, cfg: VehicleConfig | None = None) -> dict:
    """Hover at the hover thrust after an initial body-rate kick (rad/s about x and y).

    Returns the largest altitude deviation [m], the final tilt [deg] and the horizontal drift [m].
    """
    cfg = cfg or VehicleConfig()
    veh = Vehicles(1, cfg)
    z0 = veh.pos_w[0, 2]
    p0 = veh.pos_w[0, :2].copy()
    veh.reset(np.array([0]), veh.pos_w.copy(), ang_vel_b=np.array([[kick_rate, -kick_rate, 0.0]]))
    cmd = np.array([[cfg.gravity, 0.0, 0.0, 0.0]])
    dz = 0.0
    for _ in range(int(round(duration / cfg.command_dt))):
        veh.step(cmd)
        dz = max(dz, abs(veh.pos_w[0, 2] - z0))
    tilt = math.degrees(math.acos(np.clip(veh.R_wb[0, 2, 2], -1.0, 1.0)))
    return {
        "max_altitude_error_m": dz,
        "final_tilt_deg": tilt,
        "xy_drift_m": float(np.linalg.norm(veh.pos_w[0, :2] - p0)),
    }


def tilt_acceleration(tilt_deg: float = 15.0, duration: float = 2.0, cfg: VehicleConfig | None = None) -> dict:
    """Command a constant pitch at level-flight thrust; compare forward acceleration to g tan(tilt) - drag(v).

    The drag prediction uses the model's own coefficients and the measured velocity, so the comparison isolates
    the inner loop and the thrust/attitude tracking. Returns the measured and predicted accelerations at the end.
    """
    cfg = cfg or VehicleConfig()
    veh = Vehicles(1, cfg)
    th = math.radians(tilt_deg)
    cmd = np.array([[cfg.gravity / math.cos(th), 0.0, th, 0.0]])
    n = int(round(duration / cfg.command_dt))
    vel = np.empty((n, 3))
    for k in range(n):
        veh.step(cmd)
        vel[k] = veh.vel_w[0]
    dt = cfg.command_dt
    a_meas = (vel[-1] - vel[-3]) / (2 * dt)  # central difference at the step before last
    v = vel[-2]
    # Predicted: thrust g/cos(th) along z_b = (sin th, 0, cos th), gravity, and the model's drag at v.
    r = np.array([[math.cos(th), 0.0, math.sin(th)], [0.0, 1.0, 0.0], [-math.sin(th), 0.0, math.cos(th)]])
    a_cfg = cfg.airframe
    drag = -r @ (np.array(a_cfg.linear_drag) * (r.T @ v))
    drag -= 0.5 * a_cfg.air_density * a_cfg.quadratic_drag_area * np.linalg.norm(v) * v / a_cfg.mass
    a_pred = cfg.gravity / math.cos(th) * r[:, 2] - np.array([0.0, 0.0, cfg.gravity]) + drag
    return {
        "tilt_deg": tilt_deg,
        "speed_m_s": float(np.linalg.norm(v)),
        "accel_measured": a_meas,
        "accel_predicted": a_pred,
        "accel_no_drag": cfg.gravity * math.tan(th),
    }
