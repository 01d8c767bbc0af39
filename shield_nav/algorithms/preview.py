"""A receding-horizon preview tracker: linear-quadratic MPC on the attitude loop's first-order model.

The planning expert (:mod:`shield_nav.algorithms.expert`) plans a path and a speed profile along it. Its ``tangent``
tracker turns them into an acceleration with a velocity loop, a cross-track term and a partial feedforward; it reads one
reference sample and so reacts to a bend once the vehicle is in it. This tracker looks ahead: it times the planned
path into a reference trajectory and chooses the acceleration command that, for the inner loop's nominal model,
tracks the next ``steps x dt`` seconds of that trajectory best.

**Model** (per world axis, the three axes alike). State ``x = [p, v, a]``: position, velocity and the thrust
vector's acceleration (gravity removed). The attitude and thrust loops follow the commanded acceleration ``u`` to
first order, ``a' = (u - a) / tau`` (tau 0.15 s fitted on this vehicle, docs/lab-log.md 2026-11-27; docs/vehicle.md
gives the attitude loop's 0.154 s), and ``v' = a + d`` with ``d`` the nominal drag, held over the horizon. The input
is held over each of the ``steps`` intervals of ``dt`` (zero-order hold) and the model is discretised exactly.

**Cost.** ``sum_k q_pos |p_k - r_k|^2 + q_vel |v_k - w_k|^2`` over ``k = 1..steps`` (``r``, ``w`` the reference
positions and velocities) ``+ r_acc sum_k |u_k|^2 + r_jerk sum_k |u_k - u_{k-1}|^2`` with ``u_{-1}`` the thrust
acceleration now. Without constraints the minimiser is linear in the reference, the state and the drag, so the
first input is a fixed linear map (:class:`PreviewGains`), computed once: no solver, no per-env loop. Only that
first input is applied; the next control step solves again from the new state (receding horizon). The tilt and
thrust limits are applied afterwards (:func:`shield_nav.algorithms.tracking.accel_to_command`).

**Reference** (:func:`timed_reference`). The path is timed by a forward pass from the vehicle's current speed,
``w_{i+1} = min(v_{i+1}, sqrt(w_i^2 + 2 accel ds_i))`` under the planned profile ``v``, so the reference never runs
ahead of what the vehicle can reach from where it is; then sampled at ``t = dt, 2 dt, ..., steps dt``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm


def discretise(tau: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation ``x+ = A x + B u + E d`` of ``p' = v, v' = a + d, a' = (u - a) / tau``.

    Returns ``A (3, 3)``, ``B (3,)`` and ``E (3,)`` for the state ``[p, v, a]``.
    """
    if tau <= 0 or dt <= 0:
        raise ValueError(f"tau and dt must be > 0, got tau={tau}, dt={dt}")
    m = np.zeros((5, 5))
    m[0, 1] = 1.0
    m[1, 2] = 1.0
    m[2, 2] = -1.0 / tau
    m[2, 3] = 1.0 / tau  # input u
    m[1, 4] = 1.0  # disturbance d on v'
    e = expm(m * dt)
    return e[:3, :3], e[:3, 3], e[:3, 4]


def prediction(tau: float, dt: float, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stacked predictions of ``[p_k, v_k]`` for ``k = 1..steps``: ``Y = Phi x0 + Gamma U + Psi d``.

    Returns ``Phi (2 steps, 3)``, ``Gamma (2 steps, steps)``, ``Psi (2 steps,)``; rows alternate p and v.
    """
    a, b, e = discretise(tau, dt)
    c = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    phi = np.zeros((2 * steps, 3))
    gamma = np.zeros((2 * steps, steps))
    psi = np.zeros(2 * steps)
    a_pow = [np.eye(3)]
    for _ in range(steps):
        a_pow.append(a @ a_pow[-1])
    for k in range(1, steps + 1):
        rows = slice(2 * (k - 1), 2 * k)
        phi[rows] = c @ a_pow[k]
        for j in range(k):
            gamma[rows, j] = c @ a_pow[k - 1 - j] @ b
        psi[rows] = c @ sum(a_pow[k - 1 - j] @ e for j in range(k))
    return phi, gamma, psi


@dataclass(frozen=True)
class PreviewGains:
    """The first input of the unconstrained LQ tracking problem as a linear map.

    ``u_0 = ref @ k_ref - x0 @ k_state - d * k_drag + u_prev * k_prev``, with ``ref`` the stacked reference
    ``[r_1, w_1, r_2, w_2, ...]`` (per axis) and ``x0 = [p, v, a]``.
    """

    k_ref: np.ndarray
    """(2 steps,) gains on the stacked reference."""
    k_state: np.ndarray
    """(3,) gains on the state."""
    k_drag: float
    """Gain on the drag acceleration."""
    k_prev: float
    """Gain on the thrust acceleration now (the jerk penalty's anchor)."""

    @classmethod
    def build(cls, tau: float, dt: float, steps: int, q_pos: float, q_vel: float, r_acc: float,
              r_jerk: float) -> PreviewGains:  # fmt: skip
        """Gains of the cost in the module docstring."""
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        if min(q_pos, q_vel, r_acc, r_jerk) < 0 or q_pos + q_vel <= 0 or r_acc + r_jerk <= 0:
            raise ValueError(f"weights must be >= 0 with q_pos + q_vel > 0 and r_acc + r_jerk > 0, got q_pos="
                             f"{q_pos}, q_vel={q_vel}, r_acc={r_acc}, r_jerk={r_jerk}")  # fmt: skip
        phi, gamma, psi = prediction(tau, dt, steps)
        q = np.tile([q_pos, q_vel], steps)
        diff = np.eye(steps) - np.eye(steps, k=-1)  # rows: u_0 - u_{-1}, u_1 - u_0, ...
        hess = gamma.T @ (q[:, None] * gamma) + r_acc * np.eye(steps) + r_jerk * diff.T @ diff
        first = np.linalg.solve(hess, np.eye(steps)[:, 0])  # row 0 of the inverse (hess is symmetric)
        k_ref = first @ gamma.T * q  # (2 steps,)
        e0 = np.zeros(steps)
        e0[0] = 1.0
        return cls(k_ref=k_ref, k_state=k_ref @ phi, k_drag=float(k_ref @ psi),
                   k_prev=float(r_jerk * first @ diff.T @ e0))  # fmt: skip

    def first_input(self, ref: np.ndarray, x0: np.ndarray, d: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """First inputs (...,) for stacked references (..., 2 steps), states (..., 3), drags and anchors (...)."""
        return ref @ self.k_ref - x0 @ self.k_state - d * self.k_drag + u_prev * self.k_prev


def timed_reference(path: np.ndarray, v_prof: np.ndarray, speed0: np.ndarray, accel: float, dt: float,
                    steps: int) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Reference positions and velocities (N, steps, 3) at ``t = dt .. steps dt`` along paths (N, K+1, 3).

    The speed along the path is the forward pass of the module docstring from ``min(speed0, v_prof[:, 0])`` under
    the profile ``v_prof`` (N, K+1); beyond the path's end the reference stays at its last sample.
    """
    n, kp1, _ = path.shape
    seg = np.diff(path, axis=1)
    seglen = np.linalg.norm(seg, axis=2)
    tan = seg / np.maximum(seglen, 1e-9)[..., None]
    w = np.empty((n, kp1))
    w[:, 0] = np.minimum(speed0, v_prof[:, 0])
    for i in range(kp1 - 1):
        w[:, i + 1] = np.minimum(v_prof[:, i + 1], np.sqrt(w[:, i] ** 2 + 2.0 * accel * seglen[:, i]))
    dts = 2.0 * seglen / np.maximum(w[:, :-1] + w[:, 1:], 1e-6)
    t = np.concatenate((np.zeros((n, 1)), np.cumsum(dts, axis=1)), axis=1)  # (N, K+1), non-decreasing
    tq = dt * np.arange(1, steps + 1)
    idx = np.clip((t[:, None, :] <= tq[None, :, None]).sum(axis=2) - 1, 0, kp1 - 2)  # segment of each query
    r = np.arange(n)[:, None]
    span = t[r, idx + 1] - t[r, idx]
    f = np.clip((tq[None, :] - t[r, idx]) / np.maximum(span, 1e-9), 0.0, 1.0)
    pos = path[r, idx] + f[..., None] * seg[r, idx]
    speed = w[r, idx] + f * (w[r, idx + 1] - w[r, idx])
    beyond = tq[None, :] > t[:, -1:]
    speed = np.where(beyond, 0.0, speed)
    return pos, speed[..., None] * tan[r, idx]
