"""The planning expert's geometry.

Path tracing and band kernels (numba), resampling, curvature, the speed profile, which path samples the camera sees,
and the drag model; used by :mod:`shield_nav.algorithms.expert`.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from envs.fields.lookup import trilinear_batch, trilinear_point
from envs.vehicle.rotations import wrap_pi


@numba.njit(cache=True, fastmath=False)
def _unit3(x: float, y: float, z: float) -> tuple[float, float, float]:
    n = max(math.sqrt(x * x + y * y + z * z), 1e-9)
    return x / n, y / n, z / n


@numba.njit(cache=True, fastmath=False)
def _phi_at(i: int, x: float, y: float, z: float, fallback: np.ndarray, p: tuple, q: tuple, g: np.ndarray) -> float:
    """Phi of env ``i`` at one point: the inflated field ``p``, or the narrow field ``q`` where ``fallback[i]``.

    ``g`` is any (M, 3) array (the lookup's unused gradient argument must type as one).
    """
    f = q if fallback[i] else p
    return trilinear_point(f[0][i], x, y, z, f[1], f[2], f[3], f[4], f[5], g, f[5], False, False, True)[4]


@numba.njit(cache=True, fastmath=False, parallel=True)
def _trace_kernel(
    x0: np.ndarray,
    goal: np.ndarray,
    fallback: np.ndarray,
    k_steps: int,
    h: float,
    ds: float,
    clearance_gain: float,
    d_pref: float,
    goal_switch: float,
    momentum: float,
    e: tuple,
    p: tuple,
    q: tuple,
    path: np.ndarray,
    clear: np.ndarray,
) -> None:
    """The path trace of :meth:`PlannerController.trace` for every env, envs split over numba's threads.

    Fields are tuples ``(index (N,), offset, shape, origin, res, values)``; ``e`` holds the ESDF and then its gradient.
    """
    for i in numba.prange(x0.shape[0]):  # envs are independent: numba's threads split them
        x, y, z = x0[i, 0], x0[i, 1], x0[i, 2]
        px = py = pz = 0.0
        for k in range(k_steps + 1):
            path[i, k, 0], path[i, k, 1], path[i, k, 2] = x, y, z
            d, gx, gy, gz, _ = trilinear_point(e[0][i], x, y, z, e[1], e[2], e[3], e[4], e[5], e[6], e[5],
                                               True, True, False)  # fmt: skip
            clear[i, k] = d
            if k == k_steps:
                break
            ux, uy, uz = _unit3(
                -(_phi_at(i, x + h, y, z, fallback, p, q, e[6]) - _phi_at(i, x - h, y, z, fallback, p, q, e[6])),
                -(_phi_at(i, x, y + h, z, fallback, p, q, e[6]) - _phi_at(i, x, y - h, z, fallback, p, q, e[6])),
                -(_phi_at(i, x, y, z + h, fallback, p, q, e[6]) - _phi_at(i, x, y, z - h, fallback, p, q, e[6])),
            )
            gx, gy, gz = _unit3(gx, gy, gz)
            gu = gx * ux + gy * uy + gz * uz
            w = clearance_gain * min(max(d_pref - d, 0.0), d_pref) / d_pref
            ux, uy, uz = _unit3(ux + w * (gx - gu * ux), uy + w * (gy - gu * uy), uz + w * (gz - gu * uz))
            if _phi_at(i, x, y, z, fallback, p, q, e[6]) < goal_switch:
                ux, uy, uz = _unit3(goal[i, 0] - x, goal[i, 1] - y, goal[i, 2] - z)
            if k > 0 and momentum > 0:
                ux, uy, uz = _unit3(ux + momentum * px, uy + momentum * py, uz + momentum * pz)
            px, py, pz = ux, uy, uz
            x, y, z = x + ds * ux, y + ds * uy, z + ds * uz


@numba.njit(cache=True, fastmath=False, parallel=True)
def _band_kernel(
    p: np.ndarray,
    d: np.ndarray,
    ids: np.ndarray,
    floor: np.ndarray,
    iters: int,
    step: float,
    offset: np.ndarray,
    shape: np.ndarray,
    origin: np.ndarray,
    res: np.ndarray,
    esdf: np.ndarray,
    grad: np.ndarray,
    phi: np.ndarray,
    yes: bool,
    no: bool,
) -> None:
    """The elastic band of :meth:`PlannerController._band`, in place on paths ``p`` (N, K+1, 3) and clearances ``d``.

    Each iteration: every inner sample moves ``step`` of the way to its neighbours' midpoint (Jacobi, from the
    previous iterate), a sample whose ESDF is below its env's ``floor`` is pushed out along the unit ESDF gradient
    by the shortfall, and a moved sample is kept where its ESDF is at least ``min(floor, d)``. The ESDF and its
    gradient come from the lookup's own batched pass (:func:`envs.fields.lookup.trilinear_batch`, as
    :meth:`FieldStack.esdf` reads them), and the arithmetic is numpy's order of operations, so the result is the
    numpy formulation's to the bit (tests/shield_nav/test_planner_expert.py). The lookup's want-flags come in as
    arguments (``yes`` True, ``no`` False), not literals: with literal flags LLVM specialises the fastmath lookup
    inlined here and its ESDF rounds 1 ulp away from :meth:`FieldStack.esdf`'s.
    """
    n, kp1 = d.shape
    for i in numba.prange(n):  # envs are independent: numba's threads split them
        sid = ids[i * kp1 : (i + 1) * kp1]
        q = np.empty((kp1, 3))
        dq = np.empty(kp1)
        g = np.empty((kp1, 3))
        none1 = np.empty(0)
        none3 = np.empty((0, 3))
        for _ in range(iters):
            for c in range(3):
                q[0, c] = p[i, 0, c]
                q[kp1 - 1, c] = p[i, kp1 - 1, c]
            for k in range(1, kp1 - 1):
                for c in range(3):
                    q[k, c] = p[i, k, c] + step * (0.5 * (p[i, k - 1, c] + p[i, k + 1, c]) - p[i, k, c])
            trilinear_batch(sid, q, offset, shape, origin, res, esdf, grad, phi, yes, no, no, dq, none3, none1)
            trilinear_batch(sid, q, offset, shape, origin, res, esdf, grad, phi, no, yes, no, none1, g, none1)
            for k in range(1, kp1 - 1):
                push = max(floor[i] - dq[k], 0.0)
                gn = max(math.sqrt(g[k, 0] * g[k, 0] + g[k, 1] * g[k, 1] + g[k, 2] * g[k, 2]), 1e-9)
                for c in range(3):
                    q[k, c] = q[k, c] + push * (g[k, c] / gn)
            trilinear_batch(sid, q, offset, shape, origin, res, esdf, grad, phi, yes, no, no, dq, none3, none1)
            for k in range(kp1):
                if dq[k] >= min(floor[i], d[i, k]) - 1e-9:
                    d[i, k] = dq[k]
                    for c in range(3):
                        p[i, k, c] = q[k, c]


def yaw_within(psi: np.ndarray, base: np.ndarray, range_deg: float) -> np.ndarray:
    """Yaws ``psi`` (N,) [rad] held within ``range_deg`` of ``base`` (N,).

    ``base + clip(wrap(psi - base), -range, range)`` where the lead is beyond the range, ``psi`` itself where not.
    """
    r = math.radians(range_deg)
    psi = np.asarray(psi, dtype=np.float64)
    lead = wrap_pi(psi - base)
    return np.where(np.abs(lead) <= r, psi, base + np.clip(lead, -r, r))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def drag_accel(vel: np.ndarray, R_wb: np.ndarray, airframe: Any) -> np.ndarray:
    """The nominal drag acceleration (N, 3) [m/s^2] of the vehicle model at world velocities (N, 3).

    Rotor drag ``-R diag(d) R^T v`` (``airframe.linear_drag``, body frame) plus parasitic drag
    ``-rho C_d A |v| v / (2 m)`` (docs/vehicle.md).
    """
    v_b = np.einsum("nji,nj->ni", R_wb, vel)  # R^T v
    a = -np.einsum("nij,nj->ni", R_wb, np.asarray(airframe.linear_drag) * v_b)
    k = 0.5 * airframe.air_density * airframe.quadratic_drag_area / airframe.mass
    return a - k * np.linalg.norm(vel, axis=1, keepdims=True) * vel


def _project(points: np.ndarray, paths: np.ndarray) -> tuple:
    """Feet of the perpendiculars from points (N, 3) onto every segment of their polylines (N, K+1, 3).

    Returns ``(feet (N, K, 3), distances (N, K), t (N, K) in [0, 1] along each segment, segment vectors (N, K, 3))``.
    """
    a, ab = paths[:, :-1], np.diff(paths, axis=1)
    t = np.einsum("nkd,nkd->nk", points[:, None] - a, ab) / np.maximum(np.einsum("nkd,nkd->nk", ab, ab), 1e-18)
    t = np.clip(t, 0.0, 1.0)
    feet = a + t[..., None] * ab
    return feet, np.linalg.norm(feet - points[:, None], axis=2), t, ab


def polyline_distance(points: np.ndarray, paths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) from each point (N, 3) to its polyline (N, K+1, 3), and a vertex index (N,).

    The index is the nearest segment's end closer to the foot of the perpendicular.
    """
    _, d, t, _ = _project(points, paths)
    seg = d.argmin(axis=1)
    rows = np.arange(len(points))
    return d[rows, seg], seg + (t[rows, seg] > 0.5)


def resample_ahead(points: np.ndarray, paths: np.ndarray, m: int, ds: float, blend: int) -> tuple:
    """Paths (N, m+1, 3) that start at the points (N, 3) and merge onto their polylines (N, K+1, 3).

    Sample k is the polyline's point ``k ds`` beyond the foot of the perpendicular from the point, plus the offset
    point - foot times ``max(0, 1 - k / blend)``: sample 0 is the point itself, and the offset is removed
    linearly over ``blend`` samples. Returns the paths, the distances (N,) to the polylines, and whether (N,) each
    polyline reaches ``m ds`` beyond its foot.
    """
    feet, d, t, ab = _project(points, paths)
    n = len(points)
    rows, seg = np.arange(n), d.argmin(axis=1)
    seglen = np.linalg.norm(ab, axis=2)
    cum = np.concatenate((np.zeros((n, 1)), np.cumsum(seglen, axis=1)), axis=1)
    s = cum[rows, seg, None] + t[rows, seg, None] * seglen[rows, seg, None] + ds * np.arange(m + 1)  # (N, m+1)
    reach = s[:, -1] <= cum[:, -1] + 1e-9
    idx = np.clip((cum[:, None, :] <= s[..., None]).sum(axis=2) - 1, 0, seglen.shape[1] - 1)
    r = rows[:, None]
    u = np.clip((s - cum[r, idx]) / np.maximum(seglen[r, idx], 1e-9), 0.0, 1.0)
    out = paths[r, idx] + u[..., None] * ab[r, idx]
    w = np.maximum(0.0, 1.0 - np.arange(m + 1) / max(blend, 1))
    out += w[None, :, None] * (points - feet[rows, seg])[:, None, :]
    return out, d[rows, seg], reach


def speed_profile(kappa: np.ndarray, cap: np.ndarray, lat_accel: float, brake_accel: float, ds: float,
                  min_speed: float, accel_budget: float = 0.0) -> np.ndarray:  # fmt: skip
    """Fastest speeds (N, K) along a path that respect the caps and can brake into each of them.

    ``v_k = max(min_speed, min(cap_k, sqrt(lat_accel / kappa_k)))``, then backwards
    ``v_k = min(v_k, sqrt(v_{k+1}^2 + 2 a_k ds))``: from any sample, braking reaches every later cap by the time it
    gets there. Without a budget (``accel_budget`` 0) ``a_k = brake_accel``. With one, turning and braking share it
    (a friction circle): ``a_k = min(brake_accel, sqrt(A^2 - (v_{k+1}^2 kappa)^2))`` with ``kappa`` the larger of the
    segment's two end curvatures, so a bend flown at ``A`` of lateral acceleration leaves nothing to brake with and
    the braking happens before it.
    """
    v = np.minimum(cap, np.sqrt(lat_accel / np.maximum(kappa, 1e-9)))
    v = np.maximum(v, min_speed)
    two_a_ds = 2.0 * brake_accel * ds
    if accel_budget > 0:
        kseg = np.maximum(kappa[:, :-1], kappa[:, 1:])
    for k in range(v.shape[1] - 2, -1, -1):
        if accel_budget > 0:  # braking left by the turn at the segment's slower end
            lat = v[:, k + 1] ** 2 * kseg[:, k]
            two_a_ds = 2.0 * np.minimum(brake_accel, np.sqrt(np.maximum(accel_budget**2 - lat**2, 0.0))) * ds
        v[:, k] = np.minimum(v[:, k], np.sqrt(v[:, k + 1] ** 2 + two_a_ds))
    return v


def windowed_curvature(path: np.ndarray, window: int) -> np.ndarray:
    """Curvature (N, K+1) at every sample of paths (N, K+1, 3) with spacing ~ds.

    At sample k: the angle between the tangents ``window`` segments before and after (clamped to the ends),
    divided by the arc length between their midpoints. A circle of radius R gives 1 / R.
    """
    seg = np.diff(path, axis=1)  # (N, K, 3)
    seglen = np.linalg.norm(seg, axis=2)
    tan = seg / np.maximum(seglen, 1e-9)[..., None]
    n_seg = seg.shape[1]
    idx = np.arange(n_seg + 1)
    a = np.clip(idx - window, 0, n_seg - 1)
    b = np.clip(idx + window - 1, 0, n_seg - 1)
    cos = np.clip(np.einsum("nkc,nkc->nk", tan[:, a], tan[:, b]), -1.0, 1.0)
    angle = np.arccos(cos)
    cum = np.concatenate((np.zeros((len(path), 1)), np.cumsum(seglen, axis=1)), axis=1)
    mid = 0.5 * (cum[:, :-1] + cum[:, 1:])  # arc length at each segment's midpoint (N, K)
    arc = np.maximum(mid[:, b] - mid[:, a], 1e-9)
    return np.where(b > a, angle / arc, 0.0)


def visible_samples(path: np.ndarray, cam_pos: np.ndarray, R_wc: np.ndarray, cam: Any, esdf: Any,
                    los_step: float) -> np.ndarray:  # fmt: skip
    """Which path samples (N, K+1) the depth camera sees: in its frustum and range, with a free line of sight.

    Args:
        path: Paths (N, K+1, 3) in the frame of ``cam_pos``.
        cam_pos: Optical centres (N, 3).
        R_wc: Camera rotations (N, 3, 3), columns the optical axes (x right, y down, z forward) in that frame.
        cam: A :class:`envs.camera.CameraConfig` (``hfov_deg``, ``vfov_deg``, ``max_range``).
        esdf: ``esdf(points (N, M, 3)) -> (N, M)`` signed distance to the obstacles (> 0 free).
        los_step: Largest spacing of the points checked on a line of sight [m].

    A sample is seen when its z-depth is in ``(0, max_range]``, it is inside the horizontal and vertical field of
    view, and its line of sight is clear: ``m = ceil(max_range / los_step)`` points evenly inside the segment from
    the camera, spacing ``s = |segment| / (m + 1)``, each with ESDF above ``s / 2`` (the balls cover the segment, so
    no obstacle can hide between two points). Sample 0 (the vehicle) is always seen.
    """
    n, kp1, _ = path.shape
    rel = path - cam_pos[:, None, :]
    pc = np.einsum("nji,nkj->nki", R_wc, rel)  # R_wc^T rel: camera-frame coordinates
    z = pc[..., 2]
    tan_h = math.tan(math.radians(cam.hfov_deg) / 2.0)
    tan_v = math.tan(math.radians(cam.vfov_deg) / 2.0)
    seen = (z > 0) & (z <= cam.max_range) & (np.abs(pc[..., 0]) <= z * tan_h) & (np.abs(pc[..., 1]) <= z * tan_v)
    m = max(1, math.ceil(cam.max_range / los_step))
    t = np.arange(1, m + 1) / (m + 1)
    pts = cam_pos[:, None, None, :] + t[None, None, :, None] * rel[:, :, None, :]  # (N, K+1, m, 3)
    d = np.asarray(esdf(pts.reshape(n, -1, 3))).reshape(n, kp1, m)
    half = 0.5 * np.linalg.norm(rel, axis=2) / (m + 1)
    seen &= (d > half[..., None]).all(axis=2)
    seen[:, 0] = True
    return seen


def flight_env(family: str, indices: list[int], scene_seed: int | None, speed: float, num_envs: int,
               seed: int = 0) -> Any:  # fmt: skip
    """A reset :class:`envs.navigation.NavigationEnv` for flying the expert in diagnostics.

    Rendering and the curriculum off, one target speed, the evaluation's time limit (1.5 x); ``scene_seed`` None
    keeps the family's own scenes.
    """
    from envs.navigation import NavigationEnv

    over = {"scenes.family": family, "scenes.indices": list(indices), "render_depth": False,
            "curriculum.enabled": False, "episode.target_speeds": [float(speed)], "episode.speed_range": [],
            "episode.timeout_factor": 1.5, "seed": seed}  # fmt: skip
    if scene_seed is not None:
        over["scenes.seed"] = scene_seed
    env = NavigationEnv(num_envs=num_envs, **over)
    env.reset(seed=seed)
    return env
