"""Fly an exported depth policy behind the HOCBF shield, one 10 ms control step at a time: the loop a vehicle runs.

The Full row of the paper is a depth policy whose every command passes the safety shield before the attitude loop
flies it. :class:`ShieldedPilot` is that loop without the simulator: it takes what a vehicle's own sensors and state
estimate give (the metric depth image, position, velocity, attitude) and returns the attitude-thrust command for
the PX4-style inner loop::

    from shield_nav.deploy import ShieldedPilot

    pilot = ShieldedPilot.load("checkpoints/full")           # policy.onnx + its training config, default shield
    pilot.reset(goal=[[60.0, 0.0, 1.5]], target_speed=5.0)   # one vehicle; a frame with z up from the ground
    while flying:                                            # every 10 ms
        out = pilot.step(depth_m, pos, vel_w, R_wb)          # (1, 1, 60, 100) m, (1, 3) m, (1, 3) m/s, (1, 3, 3)
        send(out.command)                                    # (1, 4): [f_n m/s^2, roll, pitch, yaw rad]

It builds the policy's state vector and reads its action with the functions the env itself uses
(:mod:`envs.navigation.interface`), with the action, camera and vehicle settings the policy was trained with, and
filters with the same :class:`~shield_nav.safety.shield.HOCBFShield` as ``eval.py``'s shielded rows, so a flight flown
through it is the evaluation's flight (tested trial for trial against ``eval.py``'s ``full`` row).

With ``handover=True`` a stalled flight (no metre closer to its goal in 5 s, or 1.5 net turns of heading in 10 s) is
flown from its stall on by the weight-free camera-map planner, behind the same shield: the ``full_handover`` row of
``eval.py`` (docs/shield.md, "Stall escape"; tested step for step against that row too). It needs the flight
volume (the operator's geofence) at ``reset``, and all vehicles start their flights together.

``python -m shield_nav.deploy [CHECKPOINT] [--family benchmark --scene 13 --speed 5]`` flies one simulated flight
through the pilot alone (the simulator only supplies the sensor readings and flies the commands) and reports the
outcome and what one control step costs, policy and shield apart.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace
from typing import Any

import numpy as np

from envs.camera import normalize_depth
from envs.config import load_config
from envs.navigation import interface as I
from envs.navigation.config import NavConfig
from shield_nav.algorithms.baselines import BaselineConfig, make_baseline
from shield_nav.evaluation.policies import LoadedPolicy, load_policy
from shield_nav.safety.escape import EscapeConfig, StallEscape
from shield_nav.safety.fence import env_fence, fence_boxes
from shield_nav.safety.shield import HOCBFShield, ShieldConfig, ShieldOutput

__all__ = ["PilotStep", "ShieldedPilot"]


@dataclasses.dataclass
class PilotStep:
    """One control step of :class:`ShieldedPilot` for N vehicles."""

    command: np.ndarray
    """The command to fly (N, 4) = [f_n m/s^2, roll, pitch, yaw rad]: the shield's output, or the policy's own
    command without a shield."""
    action: np.ndarray
    """The policy's normalised action (N, 4), clipped to [-1, 1], before the shield."""
    shield: ShieldOutput | None
    """The shield's full output (activity, correction, QP status, timing); None without a shield."""
    policy_us: float
    """Wall time of the policy network for the batch [us]."""
    handed: np.ndarray | None = None
    """(N,) bool: the vehicles whose command came from the handover planner this step; None without a handover."""


def handover_config() -> EscapeConfig:
    """The stall rules of ``eval.py``'s ``full_handover`` row (its ``escape_overrides`` in configs/eval/rows.yaml)."""
    from shield_nav.evaluation.config import load_registry

    rows, _ = load_registry()
    return dataclasses.replace(EscapeConfig(), **rows["full_handover"].escape_overrides)


class _PilotView:
    """The quantities of a navigation env that the stall rules and the camera-map planner read, from the pilot's inputs.

    One flight volume for all vehicles, no finished flights (the pilot flies until its caller stops it).
    """

    def __init__(self, n: int, camera: Any, command_dt: float, gravity: float, volume: tuple) -> None:  # noqa: D107
        lo, hi = (np.asarray(v, dtype=np.float64).reshape(3) for v in volume)
        self.num_envs = n
        self.cfg = SimpleNamespace(camera=camera, render_depth=True,
                                   vehicle=SimpleNamespace(command_dt=command_dt, gravity=gravity))  # fmt: skip
        self.scenes = [SimpleNamespace(bounds_lo=lo, bounds_hi=hi)]
        self.scene_id_buf = np.zeros(n, dtype=np.int64)
        self.frozen_buf = np.zeros(n, dtype=bool)
        # This step's readings, set by ShieldedPilot._hand_over before the rules or the planner read them.
        self.vehicles = SimpleNamespace(vel_w=None, R_wb=None)
        self.local_pos = self.goal_buf = self.target_speed_buf = self.sensor_depth_buf = None


ROTATION_TOL = 1e-3
"""How far ``R_wb^T R_wb`` may be from the identity (largest entry) before :meth:`ShieldedPilot.step` refuses the
attitude: a float32 quaternion's matrix is within 1e-6, a scaled or sheared one is not."""


class ShieldedPilot:
    """An exported depth CNN+GRU policy behind the HOCBF shield, for N vehicles, one control step per call.

    Args:
        policy: The policy (:func:`shield_nav.evaluation.policies.load_policy`). Its training config, found beside
            the export, gives the action mapping, the camera and the vehicle's gravity; a policy that reads more
            than the state vector and the image (a scene memory or a clock input) is refused.
        shield: The shield's settings; True (default): :class:`ShieldConfig`'s defaults, the shield of ``eval.py``'s
            Full row; False: the policy flies alone.
        num_vehicles: N.
        handover: Stall rules after which the camera-map planner flies a vehicle (an ``EscapeConfig`` of
            ``kind: handover``); True: those of ``eval.py``'s ``full_handover`` row; False (default): none.
        replan_delay: With a handover, the control steps between a camera-map plan's inputs and the first step that
            flies it. 0 (default): planned inline, as the ``full_handover`` row (a replan then takes 10-20 ms, over
            the 10 ms period). ``L`` >= 1: planned on a thread of the pilot's own while the control steps go on,
            and flown from ``L`` steps later (the step then waits for a plan not yet done); ``eval.py`` flies the
            same with ``--set baselines.reactive.camera_map.plan_delay_steps=L``. :meth:`close` stops the thread.

    Raises:
        ValueError: the policy reads other inputs, the shield asks to choose among hypotheses (``hypotheses``
            other than ``top``, which needs the policy's candidates; ``eval.py`` flies that), or ``handover`` is an
            escape of another kind.
    """

    def __init__(self, policy: LoadedPolicy, shield: ShieldConfig | bool = True, num_vehicles: int = 1,
                 handover: EscapeConfig | bool = False, replan_delay: int = 0) -> None:  # noqa: D107  # fmt: skip
        info = policy.info
        if not isinstance(shield, (bool, ShieldConfig)):
            raise TypeError(f"shield: {shield!r}; give a ShieldConfig, True (the default shield) or False (none)")
        if not isinstance(handover, (bool, EscapeConfig)):
            raise TypeError(f"handover: {handover!r}; give an EscapeConfig, True (full_handover's rules) or False")
        handover = handover_config() if handover is True else (None if handover is False else handover)
        if handover is not None:
            handover.validate("handover.")
            if handover.kind != "handover":
                raise ValueError(f"handover.kind: {handover.kind!r}; the pilot hands flights over ('handover'), "
                                 "eval.py flies the other escape kinds")  # fmt: skip
            if make_baseline(handover.handover_planner, BaselineConfig()).privileged:
                raise ValueError(f"handover.handover_planner: {handover.handover_planner!r} reads the scene's map, "
                                 "which a vehicle does not have; eval.py flies it as a bound")  # fmt: skip
        shield = ShieldConfig() if shield is True else (None if shield is False else shield)
        if tuple(info.state_groups) != ("state",):
            raise ValueError(f"policy {info.path!r} reads the observation groups {list(info.state_groups)}; the "
                             "pilot builds only the state vector ('state') and the depth image")  # fmt: skip
        train_env = dict(info.train_env or {})
        if train_env.get("scene_memory", {}).get("enabled") or train_env.get("episode", {}).get("clock_input"):
            raise ValueError(f"policy {info.path!r} reads a scene memory or a clock input; the pilot gives neither")
        if shield is not None and shield.hypotheses != "top":
            raise ValueError(f"shield.hypotheses: {shield.hypotheses!r}; the pilot filters the policy's own action "
                             "('top'); eval.py flies the other choices")  # fmt: skip
        if num_vehicles < 1:
            raise ValueError(f"num_vehicles: {num_vehicles}; must be >= 1")
        if not (isinstance(replan_delay, int) and replan_delay >= 0):
            raise ValueError(f"replan_delay: {replan_delay!r}; give the control steps (an int >= 0) between a "
                             "handover plan's inputs and the step that flies it")  # fmt: skip
        if replan_delay and handover is None:
            raise ValueError(f"replan_delay: {replan_delay}; it delays the handover planner's plans, so it needs "
                             "a handover")  # fmt: skip
        nav = load_config(NavConfig, overrides=train_env) if train_env else NavConfig()
        self.policy = policy
        self.action_cfg = nav.action
        self.camera = nav.camera
        self.gravity = float(nav.vehicle.gravity)
        self.num_vehicles = n = int(num_vehicles)
        self.shield = HOCBFShield(shield, self.camera) if shield is not None else None
        self.goal = np.full((n, 3), np.nan)
        self.target_speed = np.full(n, np.nan)
        self.fence = np.full((n, 2, 2), np.nan)
        self.prev_action = np.zeros((n, 4))
        self.h = policy.initial_state(n)
        self.command_dt = float(nav.vehicle.command_dt)
        self.handover = handover
        self.replan_delay = int(replan_delay)
        base = BaselineConfig()
        camera_map = dataclasses.replace(base.reactive.camera_map, plan_delay_steps=self.replan_delay)
        reactive = dataclasses.replace(base.reactive, camera_map=camera_map)
        self._planner_cfg = dataclasses.replace(base, reactive=reactive)
        # With a delay the camera-map plans run on a planning thread of their own, off the control step.
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="pilot-replan") if self.replan_delay else None
        self._view: _PilotView | None = None  # with a handover: the env-like view its rules and planner read
        self._escape: StallEscape | None = None
        self._planner: Any = None
        self._t = 0

    @classmethod
    def load(cls, path: str, shield: ShieldConfig | bool = True, num_vehicles: int = 1,
             network: str = "export", handover: EscapeConfig | bool = False, replan_delay: int = 0,
             warm_up: bool = True) -> ShieldedPilot:  # fmt: skip
        """A pilot for the policy at ``path``, read by :func:`load_policy`, warmed up (:meth:`warm_up`) by default.

        ``path``: a ``checkpoints/<name>`` folder, a run's ``exported/policy.onnx``, or with ``network="fixed_order"``
        a training checkpoint.
        """
        pilot = cls(load_policy(path, "pilot", network), shield, num_vehicles, handover, replan_delay)
        if warm_up:
            pilot.warm_up()
        return pilot

    def warm_up(self) -> float:
        """Run every part of a step once before the first flight, so that no control step pays a first call.

        The shield's and the handover planner's compiled kernels are compiled on their first call, or read from
        numba's on-disk cache where an earlier run left them, and the network runtime and the QP solver allocate on
        theirs, so without a warm-up the first steps of a flight can take seconds (measured in docs/deploy.md,
        "Warm-up"). A scratch pilot of the same policy, shield, handover, planning delay and vehicle count flies three
        steps on made-up readings (a wall 4 m ahead, seen while the shield acts; then
        handed over and planned; then no return at all), once with a float32 image and once with a float64 one (the
        kernels are compiled per type); this pilot's flights, memories and maps are untouched.
        Returns the seconds it took.
        """
        t0 = time.perf_counter()
        n = self.num_vehicles
        shield = self.shield.cfg if self.shield is not None else False
        handover = self.handover if self.handover is not None else False
        scratch = ShieldedPilot(self.policy, shield, n, handover, self.replan_delay)
        h, w = self.policy.info.depth_shape[-2:]
        pos = np.tile([5.0, 0.0, 1.5], (n, 1))
        vel, r_wb = np.tile([3.0, 0.0, 0.0], (n, 1)), np.tile(np.eye(3), (n, 1, 1))
        for dtype in (np.float32, np.float64):  # the kernels are compiled per type: a camera's image may be either
            wall, blind = np.full((n, 1, h, w), 4.0, dtype=dtype), np.zeros((n, 1, h, w), dtype=dtype)
            fence = ((0.0, -10.0), (70.0, 10.0)) if self.shield is not None and self.shield.cfg.fence else None
            scratch.reset(np.tile([60.0, 0.0, 1.5], (n, 1)), 3.0, volume=((0.0, -10.0, 0.0), (70.0, 10.0, 4.0)),
                          fence=fence)  # fmt: skip
            scratch.step(wall, pos, vel, r_wb)
            if scratch._escape is not None:
                scratch._escape.guided[:] = True  # as if every vehicle had stalled: the planner plans them next step
            scratch.step(wall, pos, vel, r_wb)
            scratch.step(blind, pos, vel, r_wb)
        scratch.close()  # waits for its planning thread's plans
        return time.perf_counter() - t0

    def close(self) -> None:
        """Stop the planning thread (``replan_delay`` >= 1) after its plans in progress; the pilot steps no more."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)

    def __enter__(self) -> ShieldedPilot:
        """``with ShieldedPilot.load(...) as pilot:`` closes the pilot when the block ends."""
        return self

    def __exit__(self, *exc: object) -> None:  # noqa: D105
        self.close()

    def reset(self, goal: Any, target_speed: Any, ids: Any = None, volume: Any = None, fence: Any = None) -> None:
        """Start flights for vehicles ``ids`` (all if None): their goal (M, 3) [m] and target speed (M,) or one [m/s].

        Zeroes their recurrent state and previous action and clears their shield memory, as a new episode does.
        With a handover: ``volume`` = (lo, hi), the flight volume's corners (3,) [m] in the goal's frame (the
        planner keeps inside it and maps within it), and every vehicle starts (``ids`` None); its stall clocks,
        maps and planner start afresh. With the shield's geofence on (``shield.fence``): ``fence`` (2, 2) or
        (M, 2, 2), the geofence ``[[x_lo, y_lo], [x_hi, y_hi]]`` [m] in the goal's frame, whose sides the shield
        keeps the vehicles inside (docs/shield.md, "Geofence").
        """
        if self.handover is not None:
            if ids is not None and len(np.unique(np.atleast_1d(ids))) != self.num_vehicles:
                raise ValueError("reset: with a handover every vehicle starts its flight together (ids=None)")
            if volume is None or np.shape(volume) != (2, 3) or not np.isfinite(np.asarray(volume, float)).all():
                raise ValueError(
                    f"reset: with a handover give volume=(lo, hi), two finite (3,) corners; got {volume!r}"
                )
        sel = np.arange(self.num_vehicles) if ids is None else np.atleast_1d(np.asarray(ids, dtype=np.int64))
        fenced = self.shield is not None and self.shield.cfg.fence
        if fenced or fence is not None:  # checked (on without a box, or a box with it off) before anything changes
            box = fence_boxes(fence, len(sel), fenced, 0.0)
        goal = np.broadcast_to(np.asarray(goal, dtype=np.float64), (len(sel), 3))
        speed = np.broadcast_to(np.asarray(target_speed, dtype=np.float64), (len(sel),))
        if not (np.isfinite(goal).all() and np.isfinite(speed).all() and (speed > 0).all()):
            raise ValueError(f"reset: goal {goal.tolist()} and target_speed {speed.tolist()} must be finite, speed > 0")
        self.goal[sel] = goal
        self.target_speed[sel] = speed
        if fenced:
            self.fence[sel] = box
        self.prev_action[sel] = 0.0
        self.h[:, sel] = 0.0
        if self.shield is not None:
            self.shield.reset(sel)
        if self.handover is not None:
            n = self.num_vehicles
            self._view = _PilotView(n, self.camera, self.command_dt, self.gravity, volume)
            self._escape = StallEscape(self.handover, n, self.command_dt, self.camera)
            self._planner = make_baseline(self.handover.handover_planner, self._planner_cfg)
            self._planner.plan_pool = self._pool
            self._t = 0

    def step(self, depth_m: np.ndarray, pos: np.ndarray, vel_w: np.ndarray, R_wb: np.ndarray) -> PilotStep:  # noqa: N803
        """One control step for all N vehicles.

        Args:
            depth_m: Metric depth images (N, 1, H, W) [m] as the camera reports them (0, negative or non-finite: no
                return).
            pos: Positions (N, 3) [m] in the goal's frame, z the height above the ground.
            vel_w: Velocities (N, 3) [m/s] in that frame.
            R_wb: Attitudes (N, 3, 3), body -> that frame: rotations (orthonormal within ``ROTATION_TOL``, det +1).

        Returns:
            The command to fly, the policy's action and the shield's output. The command's normalised equivalent is
            the next step's previous-action input, as in the env.
        """
        n = self.num_vehicles
        if np.isnan(self.target_speed).any():
            raise RuntimeError("call reset(goal, target_speed) before step()")
        shapes = {"depth_m": (depth_m, (n, *self.policy.info.depth_shape)), "pos": (pos, (n, 3)),
                  "vel_w": (vel_w, (n, 3)), "R_wb": (R_wb, (n, 3, 3))}  # fmt: skip
        for name, (arr, shape) in shapes.items():
            if np.shape(arr) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {np.shape(arr)}")
        for name in ("pos", "vel_w", "R_wb"):
            if not np.isfinite(shapes[name][0]).all():
                raise ValueError(f"{name} is not finite: {np.asarray(shapes[name][0]).tolist()}")
        r = np.asarray(R_wb, dtype=np.float64)
        off = np.abs(np.einsum("nki,nkj->nij", r, r) - np.eye(3)).max(axis=(1, 2))  # R^T R = I for a rotation
        det = np.linalg.det(r)
        wrong = (off > ROTATION_TOL) | (det <= 0.0)
        if wrong.any():
            bad = int(np.flatnonzero(wrong)[0])
            raise ValueError(f"R_wb of vehicle {bad} is not a rotation (|R^T R - I| = {off[bad]:.3g}, det = "
                             f"{det[bad]:.3g}): {r[bad].tolist()}")  # fmt: skip
        vel_b = np.einsum("nji,nj->ni", R_wb, vel_w)  # R_wb^T v_w, as the vehicle model computes it
        state = I.policy_state(pos, R_wb, vel_b, self.prev_action, self.goal, self.target_speed).astype(np.float32)
        depth = normalize_depth(depth_m, self.camera)
        t0 = time.perf_counter()
        act, self.h = self.policy.step(state, depth, self.h)
        policy_us = (time.perf_counter() - t0) * 1e6
        if not np.isfinite(act).all():
            raise FloatingPointError(f"the policy returned a non-finite action for vehicle(s) "
                                     f"{np.flatnonzero(~np.isfinite(act).all(axis=1)).tolist()}")  # fmt: skip
        act = np.clip(act, -1.0, 1.0)
        base = I.yaw_bases(self.action_cfg, R_wb, vel_w)
        cmd = I.action_to_command(act, base, self.action_cfg, self.gravity)
        handed = self._hand_over(cmd, state, depth_m, pos, vel_w, R_wb) if self.handover is not None else None
        out = None
        if self.shield is not None:
            fence = self.fence if self.shield.cfg.fence else None
            out = self.shield.filter(cmd, pos, vel_w, depth=depth_m, R_wb=R_wb, ids=np.arange(n), fence=fence)
            cmd = out.command
        if self.shield is not None or handed is not None:
            self.prev_action = np.clip(I.command_to_action(cmd, base, self.action_cfg, self.gravity), -1.0, 1.0)
        else:
            self.prev_action = act
        return PilotStep(cmd, act, out, policy_us, handed)

    def _hand_over(self, cmd: np.ndarray, state: np.ndarray, depth_m: np.ndarray, pos: np.ndarray,
                   vel_w: np.ndarray, R_wb: np.ndarray) -> np.ndarray:  # noqa: N803  # fmt: skip
        """Replace the commands of the stalled vehicles by the camera-map planner's, in place; return which.

        The order of ``eval.py``'s rollout: the stall rules read this step's state, then the planner, which maps
        every vehicle's image at every call, plans the handed ones.
        """
        view, escape = self._view, self._escape
        assert view is not None and escape is not None  # reset() made them
        lo, hi = view.scenes[0].bounds_lo, view.scenes[0].bounds_hi
        escape.apply(state, pos, self.goal, depth_m, self._t, None, (lo[:2], hi[:2]), R_wb, float(lo[2]))
        view.local_pos, view.goal_buf, view.target_speed_buf = pos, self.goal, self.target_speed
        view.vehicles.vel_w, view.vehicles.R_wb, view.sensor_depth_buf = vel_w, R_wb, depth_m
        if self._t == 0:
            self._planner.reset(view)
        handed = escape.guided.copy()
        planned = self._planner.commands(view, among=handed)
        cmd[handed] = planned[handed]
        self._t += 1
        return handed


def fly(pilot: ShieldedPilot, env: Any, start: Any, goal: Any, speed: float, yaw: float, seed: int = 0,
        real_time: bool = False) -> dict:  # fmt: skip
    """Fly one flight of a one-vehicle ``env`` (a ``NavigationEnv`` without autoreset) with ``pilot`` alone.

    The env only renders the sensor's image and flies the pilot's commands. ``real_time``: each step starts one
    control period (``command_dt``) after the last started, as on a vehicle, rather than as soon as the simulator is
    done, so a planning thread has the period's idle time; a step late for its start starts at once, and the ticks
    go on from it. Returns the outcome, the step count, the mean speed, the shield's active share, the steps flown
    by the handover planner and the per-step costs [us]: the policy network, the shield, and the whole
    :meth:`ShieldedPilot.step` (state, network, mapping, handover, shield).
    """
    obs, _ = env.reset(seed=seed, options={"scene_ids": np.zeros(1, np.int64), "start": np.asarray([start]),
                                           "goal": np.asarray([goal]), "speed": np.full(1, speed),
                                           "yaw": np.full(1, yaw)})  # fmt: skip
    volume = (env.scenes[0].bounds_lo, env.scenes[0].bounds_hi) if pilot.handover is not None else None
    fence = env_fence(env) if pilot.shield is not None and pilot.shield.cfg.fence else None
    pilot.reset(env.goal_buf, speed, volume=volume, fence=fence)
    steps, speeds, active, policy_us, shield_us, step_us, outcome = 0, [], 0, [], [], [], ""
    handed_steps = 0
    period, tick = float(env.cfg.vehicle.command_dt), time.perf_counter()
    while not outcome:
        if real_time:
            tick += period
            time.sleep(max(tick - time.perf_counter(), 0.0))
            tick = max(tick, time.perf_counter())
        t0 = time.perf_counter()
        out = pilot.step(env.sensor_depth_buf, env.local_pos, env.vehicles.vel_w, env.vehicles.R_wb)
        step_us.append((time.perf_counter() - t0) * 1e6)
        policy_us.append(out.policy_us)
        handed_steps += int(out.handed is not None and out.handed[0])
        if out.shield is not None:
            active += int(out.shield.active[0])
            shield_us.append(float(out.shield.total_us[0]))
        obs, _, _, _, info = env.step(out.action, commands=out.command)
        steps += 1
        speeds.append(float(np.linalg.norm(env.vehicles.vel_w[0])))
        for name, key in (("success", "success"), ("collision", "collision"), ("out_of_bounds", "out_of_bounds"),
                          ("timeout", "time_outs")):  # fmt: skip
            if info[key][0] and not outcome:
                outcome = name
    return {"outcome": outcome, "steps": steps, "duration_s": steps * env.cfg.vehicle.command_dt,
            "mean_speed": float(np.mean(speeds)),
            "shield_active": active / steps if shield_us else None, "handed_steps": handed_steps,
            "policy_us": np.asarray(policy_us), "shield_us": np.asarray(shield_us),
            "step_us": np.asarray(step_us)}  # fmt: skip


def fly_trial(pilot: ShieldedPilot, family: str, scene: int, speed: float, trial: int = 0,
              real_time: bool = False) -> dict:  # fmt: skip
    """Fly ``eval.py``'s pinned trial ``trial`` (seed 0) of ``family`` scene ``scene`` at ``speed`` through ``pilot``.

    The tables' conditions: clean sensor, nominal vehicle, time limit 1.5 x the straight-line time + 5 s, the
    policy's training ``action``, ``camera`` and ``vehicle`` sections; ``real_time`` as :func:`fly`. Returns
    :func:`fly`'s record.
    """
    from envs.navigation import NavigationEnv
    from envs.scenes import make_scene
    from shield_nav.evaluation.rollout import sample_trial, trial_seed

    if pilot.num_vehicles != 1:
        raise ValueError(f"fly_trial flies one vehicle; the pilot has {pilot.num_vehicles}")
    overrides = {"num_envs": 1, "scenes.family": family, "scenes.indices": [scene], "curriculum.enabled": False,
                 "autoreset": False, "episode.target_speeds": [speed], "episode.speed_range": [],
                 "episode.timeout_factor": 1.5}  # fmt: skip
    train_env = pilot.policy.info.train_env
    nav = load_config(NavConfig, overrides=overrides,
                      base=load_config(NavConfig, overrides=train_env) if train_env else None)  # fmt: skip
    nav.randomization.disable()
    env = NavigationEnv(config=nav)
    try:
        seed = trial_seed(0, family, scene, speed, trial)
        tr = sample_trial(make_scene(family, scene), env.field_stack, 0, seed,
                          nav.vehicle.airframe.collision_radius + 0.4)  # fmt: skip
        return fly(pilot, env, tr["start"], tr["goal"], speed, tr["yaw"], seed % (2**31), real_time)
    finally:
        env.close()


def _mean_p99(us: np.ndarray) -> str:
    return f"{us.mean():.0f} / {np.percentile(us, 99):.0f}"


def main(argv: list[str] | None = None) -> int:
    """Fly one simulated flight through :class:`ShieldedPilot` and print its outcome and per-step cost."""
    p = argparse.ArgumentParser(prog="python -m shield_nav.deploy", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", nargs="?", default="checkpoints/full", help="policy folder or file (default: Full)")
    p.add_argument("--family", default="benchmark", help="scene family (default: benchmark, Table II's held out)")
    p.add_argument("--scene", type=int, default=0, help="scene index in the family")
    p.add_argument("--speed", type=float, default=5.0, help="target speed [m/s]")
    p.add_argument("--trial", type=int, default=0, help="which pinned trial of eval.py's seed 0 to fly")
    p.add_argument("--no-shield", action="store_true", help="fly the policy alone")
    p.add_argument(
        "--handover",
        action="store_true",
        help="hand a stalled flight to the camera-map planner (the rules of eval.py's full_handover row)",
    )
    p.add_argument("--replan-delay", type=int, default=0, metavar="L",
                   help="with --handover: plan on a thread of its own, flown L control steps later (default 0: "
                        "inline)")  # fmt: skip
    p.add_argument("--real-time", action="store_true",
                   help="start each control step one period after the last, as on a vehicle (default: as soon as the "
                        "simulator is done)")  # fmt: skip
    p.add_argument("--shield", action="append", default=[], metavar="KEY=VALUE",
                   help="a shield parameter other than its default, e.g. depth_filter=median_cross (repeatable; "
                        "docs/shield.md, 'Parameters')")  # fmt: skip
    args = p.parse_args(argv)
    if args.shield and args.no_shield:
        p.error("--shield sets the shield's parameters; it cannot go with --no-shield")
    shield: bool | ShieldConfig = not args.no_shield
    if args.shield:
        shield = load_config(ShieldConfig, overrides=args.shield)  # ConfigError names a bad key or value
    if args.replan_delay and not args.handover:
        p.error("--replan-delay delays the handover planner's plans; it needs --handover")
    pilot = ShieldedPilot.load(args.checkpoint, shield, handover=args.handover, replan_delay=args.replan_delay)
    r = fly_trial(pilot, args.family, args.scene, args.speed, args.trial, args.real_time)
    pilot.close()
    shielded = "alone" if args.no_shield else "behind the shield"
    if args.handover:
        shielded += f", handed to the camera-map planner for {r['handed_steps'] * r['duration_s'] / r['steps']:.2f} s"
    print(f"{args.checkpoint} {shielded}, {args.family} scene {args.scene}, {args.speed:g} m/s, trial {args.trial}: "
          f"{r['outcome']} after {r['duration_s']:.2f} s at {r['mean_speed']:.2f} m/s on average")  # fmt: skip
    print(f"per control step, mean / p99: the whole step {_mean_p99(r['step_us'])} us, of which the policy "
          f"{_mean_p99(r['policy_us'])} us ({pilot.policy.info.kind})", end="")  # fmt: skip
    if len(r["shield_us"]):
        print(
            f" and the shield {_mean_p99(r['shield_us'])} us, acting on {100 * r['shield_active']:.1f} % of the steps"
        )
    else:
        print()
    period_us = 1e6 * pilot.command_dt
    over = int((r["step_us"] > period_us).sum())
    print(f"slowest step {r['step_us'].max() / 1e3:.2f} ms; {over} of {r['steps']} steps over the "
          f"{period_us / 1e3:g} ms control period" + (" (paced as on a vehicle)" if args.real_time else
                                                        " (back to back; --real-time paces them)"))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
