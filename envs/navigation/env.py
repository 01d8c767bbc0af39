"""``NavigationEnv``: N quadrotors flying procedurally generated clutter, one natively batched gymnasium VectorEnv."""

from __future__ import annotations

import math
import os
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from envs.camera import DepthCamera, DepthNoise, min_pool, normalize_depth
from envs.config import load_config
from envs.fields import scene_field_stack
from envs.fields.anchors import GoalAnchorFields
from envs.navigation import interface as I
from envs.navigation import rewards as R
from envs.navigation.config import CIRCLE_TURNS, CIRCLE_WINDOW_S, REWARD_TERMS, NavConfig
from envs.navigation.memory import SceneMemory
from envs.scenes import make_scene
from envs.scenes.families import is_training_family
from envs.vehicle.rotations import euler_zyx_to_rot, rot_to_quat
from envs.vehicle.vehicles import Vehicles

STATE_DIM = 21
"""Length of the policy's state vector (see :data:`STATE_LAYOUT`)."""
STATE_LAYOUT = (
    ("vel_b", 3, "body-frame velocity / 10 [m/s]"),
    ("R_wb", 9, "rotation matrix body->world, row-major"),
    ("prev_action", 4, "executed normalised action of the previous step"),
    ("goal_xy_h", 2, "goal offset in the heading frame / max(|offset|, 10 m)"),
    ("z", 1, "own altitude / 3 [m]"),
    ("z_goal", 1, "goal altitude / 3 [m]"),
    ("target_speed", 1, "target speed / 10 [m/s]"),
)
PRIV_EXTRA = (
    ("geodesic", 1, "geodesic distance to the goal region / 100 [m]"),
    ("esdf", 1, "ESDF at the vehicle, clipped to [-1, 5], / 5 [m]"),
    ("esdf_grad", 3, "ESDF gradient"),
    ("vel_w", 3, "world-frame velocity / 10 [m/s]"),
)
CLOCK_EXTRA = (
    ("time_left", 1, "time left to the time limit / 30 [s]"),
    ("slack", 1, "the clock observation (``episode.clock_input``)"),
)
"""Columns the critic vector gains, after the min-pooled depth, with ``episode.deadline: terminate``."""


TURN_EVERY = 10
"""Control steps between the heading samples of ``episode/circling`` (the evaluation records every 10th too)."""


class NavigationEnv(VectorEnv):
    r"""High-speed depth-based navigation through clutter: the paper's MDP, batched over N vehicles.

    One process steps all N vehicles: one MuJoCo model holds every vehicle and a tile per scene, the PX4-style
    inner loop and the depth ray caster run vectorised, and there is no per-env Python loop on the hot path.
    Autoreset mode: same step (``metadata["autoreset_mode"]``): a finished env is reset inside :meth:`step`, the
    returned observation is the new episode's first, and the last one is in ``info["final_obs"]``.

    **Action** (N, 4) in [-1, 1], mapped to the vehicle command ``[f_n, phi, theta, psi]``:

    =====  ======================================  =================================================
    index  meaning                                 mapping
    =====  ======================================  =================================================
    0      collective thrust f_n [m/s^2]           -1 -> ``thrust_min``, 0 -> g (hover), +1 -> ``thrust_max``
    1      roll reference phi [rad]                a * ``max_tilt_deg``
    2      pitch reference theta [rad]             a * ``max_tilt_deg``
    3      yaw reference psi [rad]                 yaw base + a * ``yaw_range_deg`` (relative; the base is the
                                                   current heading, or with ``yaw_base: velocity`` the
                                                   horizontal velocity's heading, :attr:`yaw_bases`)
    =====  ======================================  =================================================

    **Observation** (policy, noisy): ``{"depth": (N, 1, 60, 100) float32 in [0, 1] (inverse depth
    min_range / z, 0 = invalid), "state": (N, 21) float32}`` laid out as :data:`STATE_LAYOUT`, and with
    ``scene_memory.enabled`` also ``"memory": (N, bins)`` (:class:`envs.navigation.memory.SceneMemory`), with
    ``episode.clock_input`` also ``"clock": (N, 1)`` (:meth:`clock`). The privileged
    critic vector (noise-free state, geodesic distance, ESDF and gradient, world velocity, min-pooled clean depth)
    is ``info["critic"]`` (N, C); it is never part of the policy observation.

    **Reward**: ``r = sum_i scales[i] * r_i`` over navigation (geodesic or Euclidean progress), safety (CBF),
    smooth, collision, success, speed and height (``envs.navigation.rewards``); each term is in
    ``info["log"]["reward/<name>"]``.

    **Episode end**: terminated on collision (MuJoCo contact with an obstacle, floor or ceiling; optionally also
    ESDF < radius + ``collision_margin``), out of bounds, or success (within ``goal_radius`` of the goal);
    truncated on the time limit (``info["time_outs"]``, to bootstrap), or with ``episode.deadline: terminate``
    terminated there too (the deadline as part of the task).

    Args:
        num_envs: Number of vehicles N (overrides ``config.num_envs``).
        config: A :class:`NavConfig`, a YAML path, or None (defaults).
        overrides: Dotted overrides, a list ``["a.b=1"]`` or a mapping.
        **kwargs: More dotted overrides as keywords (``**{"reward.navigation": "euclidean"}``).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int | None = None,
        config: NavConfig | str | os.PathLike | None = None,
        overrides: list[str] | dict | None = None,
        **kwargs: Any,
    ) -> None:
        extra = dict(overrides) if isinstance(overrides, dict) else {o.split("=", 1)[0]: o.split("=", 1)[1]
                                                                     for o in (overrides or [])}  # fmt: skip
        extra.update(kwargs)
        if num_envs is not None:
            extra["num_envs"] = num_envs
        if isinstance(config, NavConfig):
            cfg = load_config(NavConfig, overrides=extra or None, base=config)
        else:
            cfg = load_config(NavConfig, files=config, overrides=extra or None)
        self.cfg = cfg
        self.num_envs = n = cfg.num_envs
        self._rng = np.random.default_rng(cfg.seed)
        # ---------------------------------------------------------------- scenes, fields, physics, camera
        sc = cfg.scenes
        self.scenes = [make_scene(sc.family, i, sc.seed) for i in sc.indices]
        # Fields are built (or read from the cache) lazily: a scene on the first reset into it, an anchor's field on
        # the first episode that draws it, so a fresh env pays only for the scenes and goals it flies.
        self.field_stack = scene_field_stack(self.scenes, sc.field_resolution, cfg.vehicle.airframe.collision_radius)
        # Goal anchors set the goal distribution for every formulation (so ablations fly the same goals); their
        # fields are the navigation potential only with the geodesic reward.
        k = cfg.episode.goal_anchors
        self.anchor_fields = GoalAnchorFields(self.scenes, self.field_stack, k, lazy=True) if k > 0 else None
        self._anchor_phi = self.anchor_fields is not None and cfg.reward.navigation == "geodesic"
        length = max(s.bounds_hi[0] - s.bounds_lo[0] for s in self.scenes)
        self.tile_offset = np.array([[k * (length + sc.tile_gap), 0.0, 0.0] for k in range(len(self.scenes))])
        world = "".join(
            s.to_mjcf_geoms(offset=tuple(self.tile_offset[k]), prefix=f"scene{k}_")
            + s.moving_mjcf_bodies(offset=tuple(self.tile_offset[k]), prefix=f"scene{k}_")
            for k, s in enumerate(self.scenes)
        )
        self.vehicles = Vehicles(n, cfg.vehicle, world_xml=world)
        self.camera = DepthCamera(cfg.camera, self.scenes)
        self.noise = DepthNoise(cfg.randomization.depth_noise, cfg.camera, n, cfg.vehicle.command_dt, self._rng)
        self._moving_scenes = [k for k, s in enumerate(self.scenes) if len(s.moving)]
        self._mocap_ids = {
            k: np.array([self.vehicles.model.body(f"scene{k}_moving{j}").mocapid[0] for j in range(len(s.moving))])
            for k, s in enumerate(self.scenes)
            if len(s.moving)
        } if self._moving_scenes else {}  # fmt: skip
        self.sim_time = 0.0
        # ---------------------------------------------------------------- spaces
        H, W = cfg.camera.height, cfg.camera.width
        self.memory = SceneMemory(cfg.scene_memory, cfg.camera, n) if cfg.scene_memory.enabled else None
        """The onboard scene memory (observation ``memory``), or None when ``scene_memory.enabled`` is false."""
        spaces = {
            "depth": gym.spaces.Box(0.0, 1.0, (1, H, W), np.float32),
            "state": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32),
        }
        if self.memory is not None:
            spaces["memory"] = gym.spaces.Box(0.0, 1.0, (self.memory.dim,), np.float32)
        if cfg.episode.clock_input:
            spaces["clock"] = gym.spaces.Box(0.0, 1.0, (1,), np.float32)
        self.single_observation_space = gym.spaces.Dict(spaces)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, n)
        self.action_space = batch_space(self.single_action_space, n)
        pr, pc = cfg.critic_depth_pool
        if H % pr or W % pc:
            raise ValueError(f"critic_depth_pool {cfg.critic_depth_pool} must divide the image {H}x{W}")
        self.critic_dim = STATE_DIM + sum(k for _, k, _ in PRIV_EXTRA) + pr * pc
        self._deadline_terminates = cfg.episode.deadline == "terminate"
        if self._deadline_terminates:
            self.critic_dim += sum(k for _, k, _ in CLOCK_EXTRA)
        lm = cfg.local_map
        gx, gy, gz = np.meshgrid(lm.xs, lm.ys, lm.zs, indexing="ij")
        self._map_offsets = np.stack((gx.ravel(), gy.ravel(), gz.ravel()), axis=1)  # (M, 3), heading frame
        self.teacher_dim = STATE_DIM + len(self._map_offsets) if lm.enabled else 0
        self._teacher: np.ndarray | None = None
        self._zero_depth = np.zeros((n, 1, H, W), dtype=np.float32)
        # ---------------------------------------------------------------- per-env buffers
        self.scene_id_buf = np.zeros(n, dtype=np.int64)
        self.level_buf = np.zeros(n, dtype=np.int64)
        self.fail_streak_buf = np.zeros(n, dtype=np.int64)
        self.goal_buf = np.zeros((n, 3))
        self.anchor_buf = np.zeros(n, dtype=np.int64)
        self.target_speed_buf = np.zeros(n)
        self.episode_length_buf = np.zeros(n, dtype=np.int64)
        self.max_episode_length_buf = np.zeros(n, dtype=np.int64)
        self.phi_prev_buf = np.zeros(n)
        self.action_hist_buf = np.zeros((n, max(cfg.randomization.action_latency_steps) + 1, 4))
        self.command_hist_buf = np.zeros((n, max(cfg.randomization.action_latency_steps) + 1, 4))
        """Commands given to ``step`` (newest first), for the latency line (``randomization.command_latency``)."""
        self.latency_buf = np.zeros(n, dtype=np.int64)
        self.exec_action_buf = np.zeros((n, 4))
        self.prev_exec_action_buf = np.zeros((n, 4))
        self.wind_buf = np.zeros((n, 3))
        self.gust_buf = np.zeros((n, 3))
        self.frozen_buf = np.zeros(n, dtype=bool)
        self.clean_depth_buf = np.full((n, 1, H, W), cfg.camera.max_range, dtype=np.float32)
        self.ep_terms_buf = np.zeros((n, len(REWARD_TERMS)))
        self.ep_speed_buf = np.zeros(n)
        self.ep_min_esdf_buf = np.zeros(n)
        # Circling (episode/circling): the unwrapped heading, sampled every TURN_EVERY steps into a ring buffer that
        # spans CIRCLE_WINDOW_S, and the episode's largest net rotation [turns] between a sample and the one a window
        # earlier (or the episode's start).
        self._turn_len = max(1, int(round(CIRCLE_WINDOW_S / (TURN_EVERY * cfg.vehicle.command_dt))))
        self.heading_prev_buf = np.zeros(n)
        self.heading_total_buf = np.zeros(n)
        self.heading_hist_buf = np.zeros((n, self._turn_len))
        self.ep_max_turns_buf = np.zeros(n)
        self._nominal = {
            "mass": self.vehicles.model.body_mass[self.vehicles.body_ids].copy(),
            "inertia": self.vehicles.model.body_inertia[self.vehicles.body_ids].copy(),
            "t_max": self.vehicles.motor_t_max.copy(),
            "tau_up": self.vehicles.motor_tau_up.copy(),
            "tau_down": self.vehicles.motor_tau_down.copy(),
            "moment": self.vehicles.moment_ratio.copy(),
            **{k: getattr(self.vehicles.controller, k).copy() for k in ("attitude_p", "rate_p", "rate_i", "rate_d")},
        }
        self._scales = np.array([cfg.reward.scales.get(t, 0.0) for t in REWARD_TERMS])
        self._obs: dict[str, np.ndarray] | None = None
        self._critic: np.ndarray | None = None
        self._field_cache: tuple | None = None

    # ================================================================================================ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset every env (or ``options["env_ids"]``).

        Options may pin ``scene_ids``, ``start``, ``goal``, ``speed`` and ``yaw`` per env (the evaluation harness
        does), each an array over ``env_ids``.
        """
        if seed is not None:
            self._rng = np.random.default_rng(seed)
            self.noise._rng = self._rng
        options = dict(options or {})
        env_ids = np.asarray(options.pop("env_ids", np.arange(self.num_envs)), dtype=np.int64)
        if len(env_ids) == self.num_envs:
            self.sim_time = 0.0  # moving obstacles restart with a full reset (their clock is shared per scene)
        if seed is not None or not hasattr(self, "_started"):
            self._started = True
            if self.curriculum_active:
                hi = min(self.cfg.curriculum.initial_max_level, len(self.scenes) - 1)
                self.level_buf[:] = self._rng.integers(0, hi + 1, self.num_envs)
            self.fail_streak_buf[:] = 0
        self._reset_idx(env_ids, **options)
        self._update_fields()
        obs = self._get_observations(force_all=True)
        return obs, self._privileged_info()

    def step(
        self, actions: np.ndarray, commands: np.ndarray | None = None
    ) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Advance every env by one 10 ms control step.

        Shapes: actions (N, 4) -> obs, reward (N,), terminated (N,), truncated (N,), info.

        ``commands`` (N, 4) = [f_n, phi, theta, psi], if given, are flown instead of the mapped actions (the
        evaluation harness passes shield-corrected or baseline commands this way), through the same latency line
        (``randomization.command_latency``); the previous-action observation then holds the flown command's
        normalised equivalent (:meth:`command_to_action`, clipped to [-1, 1]).
        """
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        act = np.asarray(actions, dtype=np.float64)
        if act.shape != (self.num_envs, 4):
            raise ValueError(f"actions must have shape ({self.num_envs}, 4), got {act.shape}")
        bad = ~np.isfinite(act).all(axis=1)
        if bad.any():
            raise ValueError(f"non-finite action for env index(es) {np.flatnonzero(bad).tolist()}: {act[bad]}")
        if commands is not None:
            commands = np.asarray(commands, dtype=np.float64)
            if commands.shape != (self.num_envs, 4) or not np.isfinite(commands).all():
                bad = np.flatnonzero(~np.isfinite(commands).all(axis=1)).tolist() if commands.ndim == 2 else []
                raise ValueError(f"commands must be finite with shape ({self.num_envs}, 4); bad env(s) {bad}")
            act = np.clip(self.command_to_action(commands), -1.0, 1.0)
        cmd = self._pre_physics_step(np.clip(act, -1.0, 1.0), commands)
        collided = self.vehicles.step(cmd)
        self.sim_time += self.cfg.vehicle.command_dt
        self._move_obstacles()
        self.episode_length_buf += 1
        self._update_fields()
        collision, oob, success, timeout = self._get_dones(collided)
        # Leaving the flight volume is a failure like a collision: without the penalty, ending the episode is a free
        # escape from the negative shaping terms, and PPO with a long horizon learns to fly out of bounds.
        terms = self._get_rewards(collision | oob, success)
        reward = terms @ self._scales
        ended = collision | oob | success
        if self._deadline_terminates:
            ended = ended | timeout  # the deadline is part of the task: a time-out ends the return
        terminated = ended & ~self.frozen_buf
        truncated = timeout & ~terminated & ~self.frozen_buf
        reward[self.frozen_buf] = 0.0
        done = terminated | truncated
        info = self._log(terms, done, collision, oob, success, timeout)
        info["time_outs"] = truncated.copy()
        info["success"], info["collision"], info["out_of_bounds"] = success & done, collision & done, oob & done
        done_ids = np.flatnonzero(done)
        if len(done_ids):
            final = self._get_observations(force_all=True)
            info["final_obs"] = {k: v[done_ids].copy() for k, v in final.items()}
            info["final_obs_ids"] = done_ids
            self._update_curriculum(done_ids, success[done_ids])
            if self.cfg.autoreset:
                self._reset_idx(done_ids)
                self._update_fields()
            else:
                self.frozen_buf[done_ids] = True
        obs = self._get_observations()
        info.update(self._privileged_info())
        return obs, reward, terminated, truncated, info

    def _privileged_info(self) -> dict[str, np.ndarray]:
        """``critic`` (N, C) always; ``teacher`` (N, T) when ``local_map.enabled``."""
        out = {"critic": self._critic.copy()}
        if self._teacher is not None:
            out["teacher"] = self._teacher.copy()
        return out

    # ================================================================================================ step stages
    def _pre_physics_step(self, action: np.ndarray, commands: np.ndarray | None = None) -> np.ndarray:
        """Latency line, action -> command mapping, wind. Returns commands (N, 4)."""
        cfg = self.cfg
        hist = self.action_hist_buf
        hist[:, 1:] = hist[:, :-1]
        hist[:, 0] = action
        self.prev_exec_action_buf[:] = self.exec_action_buf
        if commands is None:
            self.exec_action_buf[:] = hist[np.arange(self.num_envs), self.latency_buf]
            cmd = self.action_to_command(self.exec_action_buf)
        elif cfg.randomization.command_latency and self.command_hist_buf.shape[1] > 1:
            # The latency line delays the commands as it delays the actions: the command flown now was given
            # latency steps ago (a fresh episode's history holds the hover command at the start heading).
            c_hist = self.command_hist_buf
            c_hist[:, 1:] = c_hist[:, :-1]
            c_hist[:, 0] = commands
            cmd = c_hist[np.arange(self.num_envs), self.latency_buf]
            self.exec_action_buf[:] = np.clip(self.command_to_action(cmd), -1.0, 1.0)
        else:
            self.exec_action_buf[:] = action
            cmd = commands.copy()
        cmd[self.frozen_buf] = np.array([cfg.vehicle.gravity, 0.0, 0.0, 0.0])
        # Gusts: Ornstein-Uhlenbeck with 1 s correlation: g += -g dt/tau + sigma sqrt(2 dt / tau) N(0, 1).
        r = cfg.randomization
        dt, tau = cfg.vehicle.command_dt, 1.0
        if r.gust_std > 0:
            self.gust_buf += -self.gust_buf * dt / tau + r.gust_std * math.sqrt(2 * dt / tau) * self._rng.normal(
                size=self.gust_buf.shape
            )
            self.gust_buf[:, 2] = 0.0
        self.vehicles.ext_force_w[:] = self.wind_buf + self.gust_buf
        return cmd

    @property
    def headings(self) -> np.ndarray:
        """Heading of every vehicle (N,) [rad]: the yaw of the body x axis, the camera's axis on the ground."""
        return I.headings(self.vehicles.R_wb)

    @property
    def yaw_bases(self) -> np.ndarray:
        """The heading (N,) [rad] the yaw action leads from (``action.yaw_base``).

        ``heading``: :attr:`headings`. ``velocity``: the horizontal velocity's heading, blended towards the current
        heading below ``yaw_base_speed`` (weight ``min(|v_h| / yaw_base_speed, 1)`` on the wrapped difference), so
        the base is continuous through hover and equal to the heading at rest.
        """
        return I.yaw_bases(self.cfg.action, self.vehicles.R_wb, self.vehicles.vel_w)

    def action_to_command(self, action: np.ndarray) -> np.ndarray:
        """Map normalised actions (N, 4) to vehicle commands (N, 4) = [f_n, phi, theta, psi] (see class doc)."""
        return I.action_to_command(action, self.yaw_bases, self.cfg.action, self.cfg.vehicle.gravity)

    def command_to_action(self, command: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`action_to_command` at the current yaw bases (unclipped). (N, 4) -> (N, 4)."""
        return I.command_to_action(command, self.yaw_bases, self.cfg.action, self.cfg.vehicle.gravity)

    def _update_fields(self) -> None:
        """Privileged fields at the current vehicle positions (scene frame)."""
        pos = self.local_pos
        esdf, grad, phi = self.field_stack.query(self.scene_id_buf, pos, geodesic=not self._anchor_phi)
        if self.cfg.reward.navigation == "euclidean":
            phi = np.linalg.norm(self.goal_buf - pos, axis=1)
        elif self._anchor_phi:
            phi = self.anchor_fields.geodesic(self.scene_id_buf, self.anchor_buf, pos)
        self._field_cache = (pos, esdf, grad, phi)

    @property
    def curriculum_active(self) -> bool:
        """Whether resets draw each env's scene from its level (a training family with the curriculum on)."""
        return bool(self.cfg.curriculum.enabled and is_training_family(self.cfg.scenes.family))

    @property
    def local_pos(self) -> np.ndarray:
        """Vehicle positions (N, 3) in each env's own scene frame [m]."""
        return self.vehicles.pos_w - self.tile_offset[self.scene_id_buf]

    def _get_dones(self, collided: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.cfg
        pos, esdf, _, _ = self._field_cache
        radius = cfg.vehicle.airframe.collision_radius
        collision = collided.copy()
        if cfg.collision_margin > 0:
            collision |= esdf < radius + cfg.collision_margin
        lo = np.array([s.bounds_lo for s in self.scenes])[self.scene_id_buf]
        hi = np.array([s.bounds_hi for s in self.scenes])[self.scene_id_buf]
        m = cfg.episode.out_of_bounds_margin
        oob = np.any(pos[:, :2] < lo[:, :2] - m, axis=1) | np.any(pos[:, :2] > hi[:, :2] + m, axis=1)
        oob |= (pos[:, 2] < lo[:, 2] - 0.5) | (pos[:, 2] > hi[:, 2] + 1.0)
        oob &= ~collision
        success = (np.linalg.norm(pos - self.goal_buf, axis=1) < cfg.episode.goal_radius) & ~collision & ~oob
        timeout = self.episode_length_buf >= self.max_episode_length_buf
        return collision, oob, success, timeout

    def _get_rewards(self, collision: np.ndarray, success: np.ndarray) -> np.ndarray:
        """The seven unscaled terms, (N, 7) in REWARD_TERMS order."""
        rc = self.cfg.reward
        pos, esdf, grad, phi = self._field_cache
        vel = self.vehicles.vel_w
        terms = np.empty((self.num_envs, len(REWARD_TERMS)))
        terms[:, 0] = R.navigation(self.phi_prev_buf, phi, rc.nav_lambda, rc.nav_clamp)
        terms[:, 1] = R.safety(esdf, grad, vel, rc.cbf_gamma, rc.cbf_d_safe, rc.cbf_delta_min)
        terms[:, 2] = R.smooth(self.exec_action_buf, self.prev_exec_action_buf, rc.smooth_magnitude)
        terms[:, 3] = R.collision(collision)
        terms[:, 4] = R.success(success)
        terms[:, 5] = R.speed(vel, self.target_speed_buf)
        terms[:, 6] = R.height(pos[:, 2], *rc.height_band)
        self.phi_prev_buf[:] = phi
        return terms

    def _get_observations(self, force_all: bool = False) -> dict[str, np.ndarray]:
        """Render, apply the sensor model, and assemble policy and critic observations."""
        cfg = self.cfg
        pos, esdf, grad, phi = self._field_cache
        r_wb = self.vehicles.R_wb
        if cfg.render_depth:
            due = np.ones(self.num_envs, dtype=bool) if force_all else self.noise.due()
            due &= ~self.frozen_buf | force_all
            ids = np.flatnonzero(due)
            if len(ids):
                self.clean_depth_buf[ids] = self.camera.render(pos[ids], r_wb[ids], self.scene_id_buf[ids])
            captured = self.noise.due() if self.memory is not None else None  # new frames this step
            noisy = self.noise.apply(self.clean_depth_buf, self._rng)
            self.sensor_depth_buf = noisy  # metric depth as the sensor reports it (what the shield may use)
            depth = normalize_depth(noisy, cfg.camera)
            if self.memory is not None:
                self.memory.push(noisy, pos, r_wb, captured)
        else:
            self.sensor_depth_buf = self.clean_depth_buf  # never rendered: max range everywhere
            depth = self._zero_depth
        clean_state = self._state(pos, r_wb, self.vehicles.vel_b)
        # Policy state: observation noise on velocity and attitude.
        rnd = cfg.randomization
        v_b = self.vehicles.vel_b + rnd.vel_noise_std * self._rng.normal(size=(self.num_envs, 3))
        if rnd.att_noise_std_deg > 0:
            e = np.radians(rnd.att_noise_std_deg) * self._rng.normal(size=(self.num_envs, 3))
            r_obs = r_wb @ euler_zyx_to_rot(e[:, 0], e[:, 1], e[:, 2])
        else:
            r_obs = r_wb
        state = self._state(pos, r_obs, v_b)
        pr, pc = cfg.critic_depth_pool
        pooled = min_pool(self.clean_depth_buf, pr, pc)
        pooled = normalize_depth(pooled.reshape(self.num_envs, -1), cfg.camera)
        columns = [clean_state, phi[:, None] / 100.0, np.clip(esdf, -1.0, 5.0)[:, None] / 5.0, grad,
                   self.vehicles.vel_w / 10.0, pooled]  # fmt: skip
        clock = None
        if self._deadline_terminates or cfg.episode.clock_input:
            time_left, clock = self.clock(pos)
            if self._deadline_terminates:
                columns += [time_left[:, None] / 30.0, clock[:, None]]
        self._critic = np.concatenate(columns, axis=1).astype(np.float32)
        if cfg.local_map.enabled:
            self._teacher = np.concatenate((clean_state, self._local_map(pos, r_wb)), axis=1).astype(np.float32)
        self._obs = {"depth": depth, "state": state.astype(np.float32)}
        if self.memory is not None:
            self._obs["memory"] = self.memory.observe(pos, r_wb)
        if cfg.episode.clock_input:
            self._obs["clock"] = clock[:, None].astype(np.float32)
        return self._obs

    def clock(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The time left to each env's limit [s] (N,) and the slack observation (N,) in [0, 1].

        The slack is time left x target speed / the straight-line distance still to fly (to the goal's radius, at
        least 1 m), divided by 3 and clipped to [0, 1]: how many times over the target speed's flight time is left.
        """
        left = np.maximum(self.max_episode_length_buf - self.episode_length_buf, 0) * self.cfg.vehicle.command_dt
        to_go = np.maximum(np.linalg.norm(self.goal_buf - pos, axis=1) - self.cfg.episode.goal_radius, 1.0)
        return left, np.clip(left * self.target_speed_buf / to_go / 3.0, 0.0, 1.0)

    def _local_map(self, pos: np.ndarray, r_wb: np.ndarray) -> np.ndarray:
        """The ESDF on the heading-frame grid of :class:`LocalMapConfig` (N, M), clipped and scaled to [-1, 1]."""
        off = self._map_offsets
        psi = np.arctan2(r_wb[:, 1, 0], r_wb[:, 0, 0])
        c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
        pts = np.empty((self.num_envs, len(off), 3))
        pts[..., 0] = pos[:, 0:1] + c * off[:, 0] - s * off[:, 1]
        pts[..., 1] = pos[:, 1:2] + s * off[:, 0] + c * off[:, 1]
        pts[..., 2] = pos[:, 2:3] + off[:, 2]
        ids = np.repeat(self.scene_id_buf, len(off))
        esdf = self.field_stack.esdf(ids, pts.reshape(-1, 3)).reshape(self.num_envs, len(off))
        clip = self.cfg.local_map.clip
        return np.clip(esdf, -clip, clip) / clip

    def _state(self, pos: np.ndarray, r_wb: np.ndarray, vel_b: np.ndarray) -> np.ndarray:
        """The (N, 21) state vector of :data:`STATE_LAYOUT` from the given (possibly noisy) quantities."""
        return I.policy_state(pos, r_wb, vel_b, self.exec_action_buf, self.goal_buf, self.target_speed_buf)

    # ================================================================================================ resets
    def _reset_idx(
        self,
        env_ids: np.ndarray,
        scene_ids: np.ndarray | None = None,
        start: np.ndarray | None = None,
        goal: np.ndarray | None = None,
        speed: np.ndarray | None = None,
        yaw: np.ndarray | None = None,
    ) -> None:
        """Start new episodes for ``env_ids`` (M,): scene, start/goal, target speed, randomization, buffers."""
        cfg, rng = self.cfg, self._rng
        m = len(env_ids)
        if m == 0:
            return
        if scene_ids is None:
            scene_ids = self.level_buf[env_ids] if self.curriculum_active else rng.integers(0, len(self.scenes), m)
        scene_ids = np.asarray(scene_ids, dtype=np.int64)
        if scene_ids.min() < 0 or scene_ids.max() >= len(self.scenes):
            raise ValueError(f"scene_ids must be in 0..{len(self.scenes) - 1}")
        self.scene_id_buf[env_ids] = scene_ids
        start = self._sample_free(scene_ids, "start_region") if start is None else np.asarray(start, dtype=float)
        if self.anchor_fields is not None:
            if goal is None:
                anchor = self.anchor_fields.sample(scene_ids, rng)
                goal = self.anchor_fields.anchors[scene_ids, anchor]
            else:
                goal = np.asarray(goal, dtype=float)
                anchor = self.anchor_fields.nearest(scene_ids, goal)
            self.anchor_buf[env_ids] = anchor
        elif goal is None:
            goal = self._sample_free(scene_ids, "goal_region")
        goal = np.asarray(goal, dtype=float)
        if speed is None:
            e = cfg.episode
            speed = rng.uniform(*e.speed_range, m) if e.speed_range else rng.choice(e.target_speeds, m)
        speed = np.asarray(speed, dtype=float)
        if yaw is None:
            to_goal = np.arctan2(goal[:, 1] - start[:, 1], goal[:, 0] - start[:, 0])
            cone = math.radians(cfg.episode.yaw_cone_deg)
            yaw = to_goal + rng.uniform(-cone, cone, m)
        yaw = np.asarray(yaw, dtype=float)
        frac = rng.uniform(*cfg.episode.initial_speed_fraction, m)
        vel0 = np.stack((np.cos(yaw), np.sin(yaw), np.zeros(m)), axis=1) * (frac * speed)[:, None]
        quat = rot_to_quat(euler_zyx_to_rot(np.zeros(m), np.zeros(m), yaw))
        self._randomize(env_ids)
        self.vehicles.reset(env_ids, start + self.tile_offset[scene_ids], quat, vel0)
        self.goal_buf[env_ids] = goal
        self.target_speed_buf[env_ids] = speed
        dist = np.linalg.norm(goal - start, axis=1)
        limit_s = cfg.episode.timeout_factor * dist / speed + 5.0
        self.max_episode_length_buf[env_ids] = np.ceil(limit_s / cfg.vehicle.command_dt).astype(np.int64)
        self.episode_length_buf[env_ids] = 0
        self.action_hist_buf[env_ids] = 0.0
        self.exec_action_buf[env_ids] = 0.0
        self.prev_exec_action_buf[env_ids] = 0.0
        self.frozen_buf[env_ids] = False
        self.ep_terms_buf[env_ids] = 0.0
        self.ep_speed_buf[env_ids] = 0.0
        self.ep_min_esdf_buf[env_ids] = np.inf
        self.heading_prev_buf[env_ids] = self.headings[env_ids]
        self.command_hist_buf[env_ids] = 0.0  # the hover command, [g, 0, 0, psi], at the start heading psi
        self.command_hist_buf[env_ids, :, 0] = cfg.vehicle.gravity
        self.command_hist_buf[env_ids, :, 3] = self.heading_prev_buf[env_ids, None]
        self.heading_total_buf[env_ids] = 0.0
        self.heading_hist_buf[env_ids] = 0.0
        self.ep_max_turns_buf[env_ids] = 0.0
        self.noise.reset(env_ids)
        if self.memory is not None:
            self.memory.reset(env_ids)
        # Potential at the start, so the first step's progress is measured from here.
        if cfg.reward.navigation == "euclidean":
            self.phi_prev_buf[env_ids] = dist
        elif self._anchor_phi:
            self.phi_prev_buf[env_ids] = self.anchor_fields.geodesic(scene_ids, self.anchor_buf[env_ids], start)
        else:
            self.phi_prev_buf[env_ids] = self.field_stack.geodesic(scene_ids, start)

    def _sample_free(self, scene_ids: np.ndarray, region: str, clearance: float = 0.4, tries: int = 20) -> np.ndarray:
        """Uniform points in each scene's region whose ESDF exceeds vehicle radius + clearance (best of tries)."""
        m = len(scene_ids)
        lo = np.array([getattr(self.scenes[k], region)[0] for k in scene_ids])
        hi = np.array([getattr(self.scenes[k], region)[1] for k in scene_ids])
        out = self._rng.uniform(lo, hi)
        need = self.cfg.vehicle.airframe.collision_radius + clearance
        ok = self.field_stack.esdf(scene_ids, out) > need
        for _ in range(tries):
            if ok.all():
                break
            redo = np.flatnonzero(~ok)
            out[redo] = self._rng.uniform(lo[redo], hi[redo])
            ok[redo] = self.field_stack.esdf(scene_ids[redo], out[redo]) > need
        return out if m else np.zeros((0, 3))

    def _randomize(self, env_ids: np.ndarray) -> None:
        """Re-sample the plant, inner loop, latency and wind of ``env_ids`` (nominal where disabled)."""
        r, rng, nom, veh = self.cfg.randomization, self._rng, self._nominal, self.vehicles
        m = len(env_ids)

        def draw(rg: Any) -> np.ndarray:
            return rng.uniform(rg.lo, rg.hi, m) if rg.enabled else np.ones(m)

        veh.set_mass_inertia(
            env_ids, nom["mass"][env_ids] * draw(r.mass_scale), nom["inertia"][env_ids] * draw(r.inertia_scale)[:, None]
        )
        veh.motor_t_max[env_ids] = nom["t_max"][env_ids] * draw(r.thrust_scale)
        veh.moment_ratio[env_ids] = nom["moment"][env_ids] * draw(r.torque_scale)
        tau = draw(r.motor_tau_scale)
        veh.motor_tau_up[env_ids] = nom["tau_up"][env_ids] * tau
        veh.motor_tau_down[env_ids] = nom["tau_down"][env_ids] * tau
        gain = draw(r.gain_scale)[:, None]
        for k in ("attitude_p", "rate_p", "rate_i", "rate_d"):
            getattr(veh.controller, k)[env_ids] = nom[k][env_ids] * gain
        lo, hi = r.action_latency_steps
        self.latency_buf[env_ids] = rng.integers(lo, hi + 1, m)
        ang = rng.uniform(0, 2 * math.pi, m)
        mag = rng.uniform(0, r.wind_max, m)
        self.wind_buf[env_ids] = np.stack((np.cos(ang) * mag, np.sin(ang) * mag, np.zeros(m)), axis=1)
        self.gust_buf[env_ids] = 0.0

    def _update_curriculum(self, env_ids: np.ndarray, succeeded: np.ndarray) -> None:
        """Up a level on success; down after ``demote_after`` consecutive failures; random level past the top."""
        if not self.curriculum_active:
            return
        c = self.cfg.curriculum
        top = len(self.scenes) - 1
        lvl = self.level_buf[env_ids]
        streak = np.where(succeeded, 0, self.fail_streak_buf[env_ids] + 1)
        lvl = np.where(succeeded, lvl + 1, lvl)
        demote = streak >= c.demote_after
        lvl = np.where(demote, lvl - 1, lvl)
        streak = np.where(demote, 0, streak)
        past_top = lvl > top
        lvl[past_top] = self._rng.integers(0, top + 1, int(past_top.sum()))
        self.level_buf[env_ids] = np.clip(lvl, 0, top)
        self.fail_streak_buf[env_ids] = streak

    def _move_obstacles(self) -> None:
        """Advance moving obstacles (dynamic family) in physics (mocap) and in the camera."""
        for k in self._moving_scenes:
            base = self.scenes[k].moving_positions(self.sim_time)
            self.camera.set_moving_positions(k, base)
            self.vehicles.data.mocap_pos[self._mocap_ids[k]] = base + self.tile_offset[k]  # body frame = base centre

    # ================================================================================================ logging
    def _log(self, terms: np.ndarray, done: np.ndarray, collision: np.ndarray, oob: np.ndarray,
             success: np.ndarray, timeout: np.ndarray) -> dict:  # fmt: skip
        """Per-step means of each scaled reward term, and per finished episode its outcome and statistics."""
        live = ~self.frozen_buf
        scaled = terms * self._scales
        self.ep_terms_buf[live] += scaled[live]
        speed = np.linalg.norm(self.vehicles.vel_w, axis=1)
        self.ep_speed_buf[live] += speed[live]
        self.ep_min_esdf_buf = np.minimum(self.ep_min_esdf_buf, self._field_cache[1])
        self._track_turns(live)
        log: dict[str, Any] = {f"reward/{t}": float(scaled[live, i].mean()) if live.any() else 0.0
                               for i, t in enumerate(REWARD_TERMS)}  # fmt: skip
        log["curriculum/mean_level"] = float(self.level_buf.mean())
        log["curriculum/max_level"] = float(self.level_buf.max())
        log["state/mean_speed"] = float(speed[live].mean()) if live.any() else 0.0
        ids = np.flatnonzero(done)
        info: dict[str, Any] = {"log": log}
        if len(ids):
            steps = np.maximum(self.episode_length_buf[ids], 1)
            log["episode/success"] = success[ids].astype(np.float64)
            log["episode/collision"] = collision[ids].astype(np.float64)
            log["episode/timeout"] = (timeout[ids] & ~(collision[ids] | oob[ids] | success[ids])).astype(np.float64)
            log["episode/out_of_bounds"] = oob[ids].astype(np.float64)
            log["episode/mean_speed"] = self.ep_speed_buf[ids] / steps
            log["episode/min_clearance"] = self.ep_min_esdf_buf[ids]
            log["episode/target_speed"] = self.target_speed_buf[ids].copy()
            log["episode/circling"] = (self.ep_max_turns_buf[ids] >= CIRCLE_TURNS).astype(np.float64)
            for i, t in enumerate(REWARD_TERMS):
                log[f"episode_reward/{t}"] = self.ep_terms_buf[ids, i].copy()
            info["episode_steps"] = steps
        return info

    def _track_turns(self, live: np.ndarray) -> None:
        """Unwrap each live vehicle's heading; every TURN_EVERY steps, its net rotation over the last window."""
        h = self.headings
        dh = (h - self.heading_prev_buf + np.pi) % (2.0 * np.pi) - np.pi
        self.heading_prev_buf = h
        self.heading_total_buf[live] += dh[live]
        k = self.episode_length_buf
        due = np.flatnonzero(live & (k % TURN_EVERY == 0))
        if len(due):
            slot = (k[due] // TURN_EVERY) % self._turn_len
            turns = np.abs(self.heading_total_buf[due] - self.heading_hist_buf[due, slot]) / (2.0 * np.pi)
            self.ep_max_turns_buf[due] = np.maximum(self.ep_max_turns_buf[due], turns)
            self.heading_hist_buf[due, slot] = self.heading_total_buf[due]

    def close(self, **kwargs: Any) -> None:  # noqa: D102
        pass
