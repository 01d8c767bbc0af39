"""A sampling tracker for the planning expert: model-predictive path integral control (MPPI) on the ESDF.

The planning expert (:mod:`shield_nav.algorithms.expert`) plans a path and a speed profile, then turns them into an
acceleration with a tracker. The ``tangent`` and ``preview`` trackers follow the plan whatever lies beside it: when
the vehicle strays (the inner loop's lag, a route that changes under it), nothing in the command knows where the
obstacles are. This tracker does: it samples acceleration sequences round its last plan, predicts each on the inner
loop's first-order model, scores the predictions on the timed reference *and on the privileged ESDF*, and applies
the cost-weighted mean of the sampled first inputs (Williams et al., "Information theoretic MPC for model-based
reinforcement learning", ICRA 2017: the path-integral weights ``exp(-(S_k - min S) / lambda)``).

**Model** (the preview tracker's, :mod:`shield_nav.algorithms.preview`): per world axis ``p' = v``, ``v' = a + d``,
``a' = (u - a) / tau``, inputs held over intervals of ``dt``, discretised exactly; ``d`` the nominal drag at the
current velocity, held. Each sampled input is clamped to the tilt cone ``|u_xy| <= (g + u_z) tan(max_tilt)`` and to
``|u_z| <= vert_accel``, as :func:`shield_nav.algorithms.tracking.accel_to_command` will clamp the command.

**Cost** of a rollout, summed over its ``steps`` predicted states ``(p_k, v_k)``:
``q_pos |p_k - r_k|^2 + q_vel |v_k - w_k|^2`` (the timed reference,
:func:`shield_nav.algorithms.preview.timed_reference`) ``+ w_clear max(0, clearance - d(p_k))^2 + w_crash [d(p_k) <
radius]`` with ``d`` the ESDF (floor and ceiling included) and ``radius`` the vehicle's collision radius, ``+ r_acc
|u_k|^2``. With a height cap ``z_cap`` (finite per env) ``d`` is ``min(ESDF, z_cap - z_k)``: the plane ``z = z_cap``
counts as one more ceiling (the expert's ``mppi_below_tops`` puts it where a sphere would pass over the obstacles'
tops).

**Samples.** ``samples`` sequences per env: sample 0 is the last plan advanced by the control period (its last
input repeated), sample 1 holds the nominal command (the preview tracker's) over the horizon, the others add Gaussian
noise of standard deviation ``sigma`` (``sigma_z`` vertically) held over ``hold`` intervals to the shifted plan.
The new plan is the weighted mean of all of them; its first input is the command. The noise comes from a generator
seeded again at every reset, so a flight repeats.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from envs.fields.lookup import trilinear_point
from shield_nav.algorithms.preview import discretise


@numba.njit(cache=True, fastmath=False, parallel=True)
def rollout_costs(
    x0: np.ndarray,
    u: np.ndarray,
    drag: np.ndarray,
    ref_p: np.ndarray,
    ref_v: np.ndarray,
    a_mat: np.ndarray,
    b_vec: np.ndarray,
    e_vec: np.ndarray,
    q_pos: float,
    q_vel: float,
    r_acc: float,
    w_clear: float,
    clearance: np.ndarray,
    w_crash: float,
    radius: float,
    e: tuple,
    out: np.ndarray,
    z_cap: np.ndarray,
) -> None:
    """Costs ``out`` (N, S) of input sequences ``u`` (N, S, T, 3) from states ``x0`` (N, 3 axes, [p, v, a]).

    ``drag`` (N, 3) is held; ``ref_p``, ``ref_v`` (N, T, 3) the reference at the ends of the T intervals;
    ``a_mat`` (3, 3), ``b_vec`` and ``e_vec`` (3,) the per-axis discretisation
    (:func:`.preview.discretise`); ``e`` the ESDF's kernel fields ``(index (N,), offset, shape, origin,
    res, esdf)``; ``z_cap`` (N,) a height per env whose plane counts as a ceiling in the clearance and crash terms
    (``inf``: none); ``clearance`` (N,) the ESDF below which each env's predicted positions pay ``w_clear``. The inputs
    must already lie in the flyable set (:func:`clamp_inputs`).
    """
    n, s_count, t_count, _ = u.shape
    for job in numba.prange(n * s_count):  # rollouts are independent: numba's threads split them
        i = job // s_count
        s = job % s_count
        st = np.empty((3, 3))  # axis, [p, v, a]
        for ax in range(3):
            for c in range(3):
                st[ax, c] = x0[i, ax, c]
        cost = 0.0
        for t in range(t_count):
            for ax in range(3):
                p, v, a = st[ax, 0], st[ax, 1], st[ax, 2]
                ui = u[i, s, t, ax]
                st[ax, 0] = a_mat[0, 0] * p + a_mat[0, 1] * v + a_mat[0, 2] * a + b_vec[0] * ui + e_vec[0] * drag[i, ax]
                st[ax, 1] = a_mat[1, 0] * p + a_mat[1, 1] * v + a_mat[1, 2] * a + b_vec[1] * ui + e_vec[1] * drag[i, ax]
                st[ax, 2] = a_mat[2, 0] * p + a_mat[2, 1] * v + a_mat[2, 2] * a + b_vec[2] * ui + e_vec[2] * drag[i, ax]
                dp = st[ax, 0] - ref_p[i, t, ax]
                dv = st[ax, 1] - ref_v[i, t, ax]
                cost += q_pos * dp * dp + q_vel * dv * dv + r_acc * ui * ui
            d = trilinear_point(e[0][i], st[0, 0], st[1, 0], st[2, 0], e[1], e[2], e[3], e[4], e[5], e[6], e[5],
                                True, False, False)[0]  # fmt: skip
            d = min(d, z_cap[i] - st[2, 0])
            gap = clearance[i] - d
            if gap > 0.0:
                cost += w_clear * gap * gap
            if d < radius:
                cost += w_crash
        out[i, s] = cost


def clamp_inputs(u: np.ndarray, gravity: float, max_tilt_deg: float, vert_accel: float) -> np.ndarray:
    """Inputs (..., 3) clamped to ``|u_z| <= vert_accel`` and then the tilt cone ``|u_xy| <= (g + u_z) tan(tilt)``."""
    out = np.array(u, dtype=np.float64, copy=True)
    out[..., 2] = np.clip(out[..., 2], -vert_accel, vert_accel)
    cap = (gravity + out[..., 2]) * math.tan(math.radians(max_tilt_deg))
    h = np.linalg.norm(out[..., :2], axis=-1)
    out[..., :2] *= np.where(h > cap, cap / np.maximum(h, 1e-12), 1.0)[..., None]
    return out


def path_integral_mean(u: np.ndarray, costs: np.ndarray, temperature: float) -> np.ndarray:
    """The weighted mean (N, T, 3) of sequences ``u`` (N, S, T, 3) under weights ``exp(-(c - min c) / lambda)``.

    ``temperature`` is lambda relative to each env's cost spread, its median cost minus its least (at least 1e-9):
    the weighting does not depend on the cost's scale, nor on how much the worst samples (a predicted crash) cost.
    Towards 0 the best sample alone; as it grows, the plain mean.
    """
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    if not np.isfinite(costs).all():
        bad = np.argwhere(~np.isfinite(costs))[0].tolist()
        raise FloatingPointError(f"MPPI: a non-finite rollout cost at (env, sample) {bad}")
    lo = costs.min(axis=1, keepdims=True)
    spread = np.maximum(np.median(costs, axis=1, keepdims=True) - lo, 1e-9)
    w = np.exp(-(costs - lo) / (temperature * spread))
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("ns,nstc->ntc", w, u)


class MppiTracker:
    """The sampling state of every env: its last plan (N, T, 3) and a seeded noise generator."""

    def __init__(self, tau: float, dt: float, steps: int, samples: int, seed: int = 0) -> None:  # noqa: D107
        if steps < 1 or samples < 3:
            raise ValueError(f"mppi needs steps >= 1 and samples >= 3, got steps={steps}, samples={samples}")
        self.a_mat, self.b_vec, self.e_vec = discretise(tau, dt)
        self.dt, self.steps, self.samples = dt, steps, samples
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.plan: np.ndarray | None = None
        self._episode: np.ndarray | None = None

    def reset(self) -> None:
        """Forget every plan and restart the noise generator (a fresh evaluation batch flies as it would first)."""
        self.rng = np.random.default_rng(self.seed)
        self.plan = None
        self._episode = None

    def warm_start(self, nominal: np.ndarray, episode_steps: np.ndarray, elapsed: float) -> np.ndarray:
        """Each env's last plan advanced by ``elapsed`` seconds; the nominal command (N, 3) held where there is none.

        The plan is read ``elapsed / dt`` intervals later (linearly between its inputs; its last input repeated
        beyond its end). An env has no plan on the first call, after :meth:`reset`, and when its episode restarted
        (its step count did not grow).
        """
        n = len(nominal)
        held = np.repeat(nominal[:, None, :], self.steps, axis=1)
        ep = np.asarray(episode_steps).copy()
        if self.plan is None or self.plan.shape[0] != n:
            self._episode = ep
            return held
        t = np.arange(self.steps) + elapsed / self.dt
        i0 = np.minimum(np.floor(t).astype(int), self.steps - 1)
        i1 = np.minimum(i0 + 1, self.steps - 1)
        f = np.clip(t - np.floor(t), 0.0, 1.0)[None, :, None]
        shifted = (1.0 - f) * self.plan[:, i0] + f * self.plan[:, i1]
        fresh = ep <= self._episode
        self._episode = ep
        return np.where(fresh[:, None, None], held, shifted)

    def candidates(self, base: np.ndarray, nominal: np.ndarray, sigma: float, sigma_z: float, hold: int) -> np.ndarray:
        """Sequences (N, S, T, 3): the base plan, the nominal command held, then the base plus held Gaussian noise."""
        n, t_count, _ = base.shape
        knots = -(-t_count // hold)
        noise = self.rng.standard_normal((n, self.samples - 2, knots, 3))
        noise[..., :2] *= sigma
        noise[..., 2] *= sigma_z
        noise = np.repeat(noise, hold, axis=2)[:, :, :t_count]
        held = np.repeat(nominal[:, None, :], t_count, axis=1)
        return np.concatenate((base[:, None], held[:, None], base[:, None] + noise), axis=1)
