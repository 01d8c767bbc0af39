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
   :class:`shield_nav.algorithms.tracking.TrackingConfig` overridden by ``max_tilt_deg``. Yaw follows the chord, so the
   camera looks along the path. ``drag_ff`` > 0 adds that share of the vehicle model's drag at the current velocity
   (:func:`drag_accel`) to ``a``; off by default (docs/expert.md, "The drag feedforward"). That is the ``chord`` /
   ``tangent`` family. ``tracker: preview`` instead chooses ``a`` by receding-horizon LQ tracking of the path timed
   by its profile, on the inner loop's first-order model (:mod:`shield_nav.algorithms.preview`). The default since
   2026-11-29, ``tracker: mppi``, samples input sequences round that preview command and scores their predictions
   on the same model against the timed path *and the ESDF*, so the command keeps clear of obstacles the plan passes
   close to (:mod:`shield_nav.algorithms.mppi`). Envs that descend the narrow field keep the ``tangent`` command under
   both.

With ``commit_dist`` 0 the expert is stateless: its command depends only on the current state, so it labels any
state a student reaches (DAgger). With route hysteresis (``commit_dist`` > 0) it also remembers each env's last path;
it is called once per env step in evaluation and in DAgger's labelling alike, and an env whose episode starts again
(or a second call without a step between) gets the fresh trace. Velocity-keyed route choice (``predict_s`` > 0)
is the Markovian alternative: the route is chosen from position and velocity, no memory. It reads the map, so it is
**privileged**: an upper bound, not a competitor.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from shield_nav.algorithms.expert_config import (
    ExpertConfig,
)
from shield_nav.algorithms.expert_paths import (
    _band_kernel,
    _trace_kernel,
    _unit,
    drag_accel,
    polyline_distance,
    resample_ahead,
    speed_profile,
    visible_samples,
    windowed_curvature,
    yaw_within,
)
from shield_nav.algorithms.mppi import MppiTracker, clamp_inputs, path_integral_mean, rollout_costs
from shield_nav.algorithms.preview import PreviewGains, timed_reference
from shield_nav.algorithms.tracking import accel_to_command


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
        """Accelerations (N, 3) of the ``mppi`` tracker (:mod:`.mppi`) round the nominal command."""
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
