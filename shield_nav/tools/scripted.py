"""Scripted flights for the shield: a naive goal-seeking controller flown straight at a pole or a wall.

No learned policy is involved. The controller tracks a constant-speed velocity towards the goal and ignores
obstacles entirely, so without the shield it crashes; the full vehicle simulation (MuJoCo physics and contacts,
PX4-style inner loop) and the depth camera are real. Used by the shield tests, its benchmark and docs/shield.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from envs.camera import CameraConfig, DepthCamera
from envs.scenes.primitives import Box, Cylinder
from envs.vehicle.config import VehicleConfig
from envs.vehicle.vehicles import Vehicles
from shield_nav.safety.shield import HOCBFShield, ShieldConfig, command_from_accel

OBSTACLE_X = 12.0
"""Distance from the start to the obstacle's near side [m]."""


OBSTACLE_TOP = 4.0
"""Height of the pole's and the wall's top [m]; a correction can lift the vehicle over it."""


def obstacle(kind: str) -> tuple[list, callable]:
    """The primitives of a test obstacle and a function giving the distance from points (N, 3) to its surface.

    The distance is Euclidean in 3-D (to the nearest point of the solid, 0 inside it), so a vehicle that passes
    over the top or around an end is measured as far as it really is.
    """
    if kind == "pole":
        r = 0.15
        prims = [Cylinder((OBSTACLE_X + r, 0.0, 0.0), (OBSTACLE_X + r, 0.0, OBSTACLE_TOP), r)]

        def dist(p: np.ndarray) -> np.ndarray:
            radial = np.maximum(np.hypot(p[:, 0] - (OBSTACLE_X + r), p[:, 1]) - r, 0.0)
            above = np.maximum(p[:, 2] - OBSTACLE_TOP, 0.0)
            return np.hypot(radial, above)

        return prims, dist
    if kind == "wall":
        half = np.array([0.1, 6.0, OBSTACLE_TOP / 2])
        centre = np.array([OBSTACLE_X + 0.1, 0.0, OBSTACLE_TOP / 2])
        prims = [Box(tuple(centre), tuple(half))]

        def dist(p: np.ndarray) -> np.ndarray:
            return np.linalg.norm(np.maximum(np.abs(p - centre) - half, 0.0), axis=1)

        return prims, dist
    raise ValueError(f"unknown obstacle kind {kind!r}; expected 'pole' or 'wall'")


def goal_seeking_command(
    pos_w: np.ndarray, vel_w: np.ndarray, goal_w: np.ndarray, speed: np.ndarray, cfg: VehicleConfig
) -> np.ndarray:
    """Naive velocity tracker: a = 2 (v_d - v) + drag compensation, v_d = speed * (goal - p)/|goal - p|.

    Horizontal acceleration is capped at g tan(40 deg); yaw faces the goal. Returns commands (N, 4).
    """
    to_goal = goal_w - pos_w
    v_d = speed[:, None] * to_goal / np.maximum(np.linalg.norm(to_goal, axis=1, keepdims=True), 1e-6)
    a = 2.0 * (v_d - vel_w)
    a += np.array(cfg.airframe.linear_drag) * v_d  # feed-forward the (roughly linear) drag at the target speed
    cap = cfg.gravity * math.tan(math.radians(40.0))
    h = np.linalg.norm(a[:, :2], axis=1, keepdims=True)
    a[:, :2] *= np.minimum(1.0, cap / np.maximum(h, 1e-9))
    a[:, 2] = np.clip(a[:, 2], -5.0, 5.0)
    psi = np.arctan2(to_goal[:, 1], to_goal[:, 0])
    return command_from_accel(a, psi, cfg.gravity)


@dataclass
class FlightLog:
    """Time series of scripted flights (T steps, N vehicles)."""

    t: np.ndarray
    """(T,) time [s]."""
    pos_w: np.ndarray
    """(T, N, 3) positions."""
    distance: np.ndarray
    """(T, N) distance from the vehicle centre to the obstacle surface [m]."""
    collided: np.ndarray
    """(N,) bool: MuJoCo reported a contact with the obstacle."""
    min_distance: np.ndarray
    """(N,) smallest distance to the obstacle surface [m]."""
    active: np.ndarray
    """(T, N) bool: shield active at that step."""
    solve_us: np.ndarray
    """(T, N) QP solver time [us] (0 when inactive)."""
    total_us: np.ndarray
    """(T, N) whole shield time [us]."""
    states: list
    """Per step: (pos_w, vel_w, R_wb, command, depth) copies, for replaying the shield in the benchmark."""


def fly(
    kind: str,
    speeds: list[float],
    shielded: bool,
    duration: float = 4.0,
    shield_cfg: ShieldConfig | None = None,
    record_states: bool = False,
) -> FlightLog:
    """Fly one vehicle per speed straight at the obstacle from 12 m away, starting at that speed, 1.5 m high."""
    vcfg = VehicleConfig()
    cam_cfg = CameraConfig()
    prims, dist = obstacle(kind)
    world = "".join(p.to_mjcf() for p in prims)
    n = len(speeds)
    veh = Vehicles(n, vcfg, world_xml=world)
    speed = np.asarray(speeds, dtype=float)
    start = np.tile([0.0, 0.0, 1.5], (n, 1))
    veh.reset(np.arange(n), start, vel_w=np.stack((speed, np.zeros(n), np.zeros(n)), axis=1))
    goal = np.tile([OBSTACLE_X + 20.0, 0.0, 1.5], (n, 1))
    camera = DepthCamera(cam_cfg, [prims])
    shield = HOCBFShield(shield_cfg, cam_cfg) if shielded else None
    steps = int(round(duration / vcfg.command_dt))
    pos = np.zeros((steps, n, 3))
    d = np.zeros((steps, n))
    active = np.zeros((steps, n), dtype=bool)
    solve_us = np.zeros((steps, n))
    total_us = np.zeros((steps, n))
    done = np.zeros(n, dtype=bool)
    states = []
    for k in range(steps):
        cmd = goal_seeking_command(veh.pos_w, veh.vel_w, goal, speed, vcfg)
        if shield is not None:
            r_wb = veh.R_wb
            depth = camera.render(veh.pos_w, r_wb)
            if record_states:
                states.append((veh.pos_w.copy(), veh.vel_w.copy(), r_wb, cmd.copy(), depth))
            out = shield.filter(cmd, veh.pos_w, veh.vel_w, depth=depth, R_wb=r_wb)
            cmd = out.command
            active[k], solve_us[k], total_us[k] = out.active, out.solve_us, out.total_us
        # Vehicles that crashed are frozen (their command is a hover) so the log shows the crash point.
        cmd[done] = np.array([vcfg.gravity, 0.0, 0.0, 0.0])
        veh.step(cmd)
        done |= veh.collided_buf
        pos[k] = veh.pos_w
        d[k] = dist(veh.pos_w)
    t = np.arange(1, steps + 1) * vcfg.command_dt
    return FlightLog(t, pos, d, veh.collided_buf.copy(), d.min(axis=0), active, solve_us, total_us, states)


def _visible_surface(kind: str, pos: np.ndarray, wall_angle_deg: float) -> np.ndarray:
    """Dense surface points of the point-mass test obstacles that face ``pos`` (and lie within 10 m of it)."""
    if kind == "pole":  # radius 0.15 m at x = 12.15 m: every 2 deg around, every 5 cm up
        ang = np.radians(np.arange(0.0, 360.0, 2.0))
        normal = np.stack((np.cos(ang), np.sin(ang)), axis=1)
        xy = np.array([OBSTACLE_X + 0.15, 0.0]) + 0.15 * normal
        xy = xy[np.sum(normal * (pos[:2] - xy), axis=1) > 0.0]
        zs = np.arange(0.2, OBSTACLE_TOP, 0.05)
    elif kind == "wall":  # through (12, 0), turned by wall_angle_deg from facing the flight, 12 m long, every 5 cm
        t = math.radians(wall_angle_deg)
        xy = np.array([OBSTACLE_X, 0.0]) + np.arange(-6.0, 6.0, 0.05)[:, None] * np.array([math.sin(t), math.cos(t)])
        zs = np.arange(0.2, OBSTACLE_TOP, 0.1)
    else:
        raise ValueError(f"unknown obstacle kind {kind!r}; expected 'pole' or 'wall'")
    pts = np.concatenate([np.column_stack((xy, np.full(len(xy), z))) for z in zs])
    return pts[np.linalg.norm(pts - pos, axis=1) < 10.0]


def point_mass_flight(
    kind: str, speed: float, shield_cfg: ShieldConfig | None = None, wall_angle_deg: float = 30.0,
    duration: float = 4.5,
) -> float:  # fmt: skip
    """Minimum distance to the surface [m] of a shielded point-mass flight at a pole or an angled wall.

    The vehicle is a double integrator that flies exactly the shield's corrected acceleration (no attitude loop,
    no lag), so what is measured is the shield's geometry alone: the naive goal-seeking acceleration
    (``2 (v_d - v)``, horizontal <= g tan 40 deg) from 12 m away at ``speed``, every visible surface point given to
    the shield each 10 ms step (a 2 deg x 5 cm sampling of the 0.15 m pole; a 5 x 10 cm sampling of a 12 m wall
    turned by ``wall_angle_deg``). The paper's one-shot selection lets it inside ``r_safe`` (docs/shield.md).
    """
    g = VehicleConfig().gravity
    shield = HOCBFShield(shield_cfg)
    pos, vel = np.array([0.0, 0.0, 1.5]), np.array([speed, 0.0, 0.0])
    goal = np.array([OBSTACLE_X + 20.0, 0.0, 1.5])
    t = math.radians(wall_angle_deg)
    wall_normal = np.array([math.cos(t), -math.sin(t)])
    dt, d_min = 0.01, math.inf
    for _ in range(int(round(duration / dt))):
        to_goal = goal - pos
        a = 2.0 * (speed * to_goal / np.linalg.norm(to_goal) - vel)
        h = np.linalg.norm(a[:2])
        cap = g * math.tan(math.radians(40.0))
        if h > cap:
            a[:2] *= cap / h
        a[2] = min(max(a[2], -5.0), 5.0)
        cmd = command_from_accel(a[None], np.zeros(1), g)
        out = shield.filter(cmd, pos[None], vel[None], points_w=[_visible_surface(kind, pos, wall_angle_deg)])
        vel = vel + dt * out.accel_safe[0]
        pos = pos + dt * vel
        if kind == "pole":
            d = math.hypot(pos[0] - (OBSTACLE_X + 0.15), pos[1]) - 0.15
        else:
            d = abs(float(np.dot(pos[:2] - np.array([OBSTACLE_X, 0.0]), wall_normal)))
        d_min = min(d_min, d)
    return d_min


def step_response(accel: float = 5.0, duration: float = 0.6) -> dict:
    """The vehicle's horizontal acceleration after a step in the commanded acceleration, from hover.

    The command is the attitude and thrust that give ``accel`` m/s^2 along x (``command_from_accel``); the
    acceleration is measured from velocity differences per command period, with the airframe's linear drag added
    back so only the thrust direction's response is seen. Returns the times [s] at which it first reaches 10, 50,
    63.2 and 90 % of its final value, and the equivalent delay (the area between the step and the response over
    the final value: the lag of a first-order model with the same area) that ``ShieldConfig.lag_s`` models.
    """
    vcfg = VehicleConfig()
    veh = Vehicles(1, vcfg, world_xml="")
    veh.reset(np.arange(1), np.array([[0.0, 0.0, 5.0]]), vel_w=np.zeros((1, 3)))
    hover = command_from_accel(np.zeros((1, 3)), np.zeros(1), vcfg.gravity)
    for _ in range(100):
        veh.step(hover)
    cmd = command_from_accel(np.array([[accel, 0.0, 0.0]]), np.zeros(1), vcfg.gravity)
    dt = vcfg.command_dt
    steps = int(round(duration / dt))
    v_prev = veh.vel_w[0, 0]
    acc = np.zeros(steps)
    for k in range(steps):
        veh.step(cmd)
        v = veh.vel_w[0, 0]
        acc[k] = (v - v_prev) / dt + vcfg.airframe.linear_drag[0] * v
        v_prev = v
    t = dt * np.arange(1, steps + 1)
    final = float(acc[-int(0.1 / dt) :].mean())
    out = {f"t{int(round(100 * f))}_s": float(t[np.argmax(acc >= f * final)]) for f in (0.1, 0.5, 0.632, 0.9)}
    out["equivalent_delay_s"] = float(np.sum(1.0 - acc / final) * dt)
    out["final_accel"] = final
    return out


def plot_flights(kind: str, speeds: list[float], path: str, duration: float = 4.5) -> dict:
    """Save a figure of distance-to-obstacle over time, shielded vs unshielded; return the minimum distances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bare = fly(kind, speeds, shielded=False, duration=duration)
    safe = fly(kind, speeds, shielded=True, duration=duration)
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    colours = plt.cm.viridis(np.linspace(0.0, 0.85, len(speeds)))
    for i, v in enumerate(speeds):
        ax.plot(safe.t, safe.distance[:, i], color=colours[i], label=f"{v:g} m/s, shield")
        cut = np.argmax(bare.distance[:, i] <= bare.min_distance[i] + 1e-9) + 1
        ax.plot(bare.t[:cut], bare.distance[:cut, i], color=colours[i], ls="--", label=f"{v:g} m/s, no shield")
        if bare.collided[i]:
            ax.plot(bare.t[cut - 1], bare.distance[cut - 1, i], "rx", ms=8)
    ax.axhline(0.2, color="r", lw=0.8, ls=":", label="collision (vehicle radius 0.2 m)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"distance to {kind} surface [m]")
    ax.set_ylim(0, 6)
    ax.set_title(f"Naive goal-seeking flight at a {kind}: HOCBF shield vs none")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return {"min_distance_shield": safe.min_distance.round(3).tolist(), "collided_no_shield": bare.collided.tolist()}


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.scripted", description=__doc__.splitlines()[0])
    ap.add_argument("--kind", default="pole", choices=["pole", "wall"])
    ap.add_argument("--speeds", default="3,5,7,9")
    ap.add_argument("--plot", help="output PNG of the shielded and unshielded flights")
    ap.add_argument("--step-response", action="store_true", help="print the vehicle's acceleration step response")
    a = ap.parse_args()
    if a.step_response:
        print({k: round(v, 3) for k, v in step_response().items()})
    if a.plot:
        print(plot_flights(a.kind, [float(s) for s in a.speeds.split(",")], a.plot))
    if not (a.plot or a.step_response):
        ap.error("give --plot PNG and/or --step-response")
