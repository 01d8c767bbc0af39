"""Sensor model for domain randomization: stereo noise, invalid pixels, flying pixels, frame rate and latency."""

from __future__ import annotations

import numba as nb
import numpy as np

from envs.camera.config import CameraConfig, DepthNoiseConfig


@nb.njit(cache=True, fastmath=False, nogil=True)
def _paint_holes(
    img: np.ndarray, env: np.ndarray, cu: np.ndarray, cv: np.ndarray, au: np.ndarray, av: np.ndarray
) -> None:
    """Zero the pixels of ``img[env[k]]`` (E, H, W) inside ellipse k (centre cu, cv; semi-axes au, av; pixels)."""
    _, H, W = img.shape
    for k in range(env.shape[0]):
        e = env[k]
        v0, v1 = max(int(np.floor(cv[k] - av[k])), 0), min(int(np.ceil(cv[k] + av[k])), H - 1)
        u0, u1 = max(int(np.floor(cu[k] - au[k])), 0), min(int(np.ceil(cu[k] + au[k])), W - 1)
        for v in range(v0, v1 + 1):
            dv = (v + 0.5 - cv[k]) / av[k]
            for u in range(u0, u1 + 1):
                du = (u + 0.5 - cu[k]) / au[k]
                if du * du + dv * dv <= 1.0:  # pixel centre inside the ellipse
                    img[e, v, u] = 0.0


class DepthNoise:
    """Per-env depth sensor model: corrupts clean frames, runs each env's frame clock, and delays frames.

    Each call of :meth:`apply` is one control step of ``control_dt`` seconds. An env *captures* a frame when its
    frame clock is due (every step when ``frame_rate_hz`` is 0); the captured clean frame is corrupted, in
    order, by:

    1. flying pixels: an edge pixel (a 4-neighbour differs by more than ``edge_threshold * z``) becomes, with
       probability ``edge_prob``, ``z + U(0, 1) * (z_n - z)`` with ``z_n`` the most different neighbour;
    2. stereo noise: ``z + N(0, (depth_sigma_coeff * z^2)^2)`` on pixels with a return (``z < max_range``),
       clipped to ``[min_range, max_range]``;
    3. too close: if ``invalid_below_min``, pixels at ``min_range`` or closer read 0;
    4. dropout: each pixel reads 0 with probability ``dropout_prob``;
    5. holes: Poisson(``holes_per_frame``) axis-aligned elliptical regions read 0.

    The frame pushed into the env's latency line is shown ``latency_frames`` captures later and held
    (zero-order hold) until the next capture. After :meth:`reset` an env captures at its next step and its
    latency line is filled with that first frame, so no frame from a previous episode leaks.

    Args:
        cfg: The sensor model configuration.
        cam_cfg: The camera (image size and ranges).
        num_envs: Number of envs N.
        control_dt: Seconds per :meth:`apply` call (the control period).
        rng: Generator for the random frame-clock phases on reset (default: seeded 0).
    """

    def __init__(
        self,
        cfg: DepthNoiseConfig,
        cam_cfg: CameraConfig,
        num_envs: int,
        control_dt: float = 0.01,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.cfg = cfg
        self.cam_cfg = cam_cfg
        self.num_envs = int(num_envs)
        self.control_dt = float(control_dt)
        self.period = 1.0 / cfg.frame_rate_hz if cfg.frame_rate_hz > 0.0 else 0.0
        self._rng = rng if rng is not None else np.random.default_rng(0)
        H, W = cam_cfg.height, cam_cfg.width
        L = cfg.latency_frames + 1
        self._line_buf = np.zeros((self.num_envs, L, H, W), dtype=np.float32)  # latency line (ring) per env
        self._head_buf = np.zeros(self.num_envs, dtype=np.int64)  # next ring slot to write
        self._clock_buf = np.zeros(self.num_envs)  # seconds until the next capture
        self._fresh_buf = np.ones(self.num_envs, dtype=bool)  # reset: capture now, fill the line
        self._out_buf = np.zeros((self.num_envs, 1, H, W), dtype=np.float32)

    def reset(self, env_ids: np.ndarray | None = None) -> None:
        """Forget the frames of ``env_ids`` (default all): they capture at their next step."""
        ids = np.arange(self.num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        self._fresh_buf[ids] = True
        self._clock_buf[ids] = 0.0

    def due(self) -> np.ndarray:
        """Bool mask (N,) of envs that capture a frame at the next :meth:`apply` (others may skip rendering)."""
        return self._fresh_buf | (self._clock_buf <= 1e-9)

    def apply(self, clean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Advance one control step and return the sensor output.

        Args:
            clean: Clean depth (N, 1, H, W) from ``DepthCamera.render``; only the rows of :meth:`due` envs are
                read (the others may be stale).
            rng: Random generator for the corruption.

        Returns:
            Depth (N, 1, H, W) float32 as the sensor reports it (invalid pixels 0); a new array.
        """
        clean = np.asarray(clean, dtype=np.float32)
        if clean.shape != self._out_buf.shape:
            raise ValueError(f"clean depth must have shape {self._out_buf.shape}, got {clean.shape}")
        due = self.due()
        ids = np.flatnonzero(due)
        if ids.size:
            frames = self._corrupt(clean[ids, 0], rng)  # (E, H, W)
            L = self._line_buf.shape[1]
            fresh = self._fresh_buf[ids]
            if fresh.any():
                self._line_buf[ids[fresh]] = frames[fresh][:, None]  # fill the whole latency line
                self._head_buf[ids[fresh]] = 0
            old = ids[~fresh]
            self._line_buf[old, self._head_buf[old]] = frames[~fresh]
            self._head_buf[old] = (self._head_buf[old] + 1) % L
            # The oldest frame in the line (the next slot to be overwritten) is L - 1 captures old.
            self._out_buf[ids, 0] = self._line_buf[ids, self._head_buf[ids]]
            # Frame clock: next capture one period later; after a reset, a random phase within one period.
            if self.period > 0.0:
                nxt = np.full(ids.size, self.period)
                if self.cfg.random_phase and fresh.any():
                    nxt[fresh] = self.period * (1.0 - self._rng.random(int(fresh.sum())))  # U(0, period]
                self._clock_buf[ids] += nxt
            self._fresh_buf[ids] = False
        if self.period > 0.0:
            self._clock_buf -= self.control_dt
        return self._out_buf.copy()

    def _corrupt(self, z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Apply the per-frame corruptions (steps 1-5 of the class docstring) to clean frames ``z`` (E, H, W)."""
        cfg, cam = self.cfg, self.cam_cfg
        z = z.copy()
        E, H, W = z.shape
        if cfg.edge_prob > 0.0:
            # Most different 4-neighbour (edge replicate at the borders).
            zp = np.pad(z, ((0, 0), (1, 1), (1, 1)), mode="edge")
            nbrs = np.stack([zp[:, :-2, 1:-1], zp[:, 2:, 1:-1], zp[:, 1:-1, :-2], zp[:, 1:-1, 2:]])  # (4, E, H, W)
            jump = nbrs - z[None]
            k = np.abs(jump).argmax(axis=0)
            jmax = np.take_along_axis(jump, k[None], axis=0)[0]
            edge = np.abs(jmax) > cfg.edge_threshold * z
            fly = edge & (rng.random(z.shape, dtype=np.float32) < cfg.edge_prob)
            z = np.where(fly, z + rng.random(z.shape, dtype=np.float32) * jmax, z)
        if cfg.depth_sigma_coeff > 0.0:
            ret = z < cam.max_range  # pixels with a return
            sigma = np.float32(cfg.depth_sigma_coeff) * z * z  # stereo: sigma_z = z^2 * sigma_disparity / (f b)
            noisy = z + sigma * rng.standard_normal(z.shape, dtype=np.float32)
            z = np.where(ret, np.clip(noisy, cam.min_range, cam.max_range), z)
        if cfg.invalid_below_min:
            z[z <= cam.min_range] = 0.0
        if cfg.dropout_prob > 0.0:
            z[rng.random(z.shape, dtype=np.float32) < cfg.dropout_prob] = 0.0
        if cfg.holes_per_frame > 0.0:
            counts = rng.poisson(cfg.holes_per_frame, size=E)
            env = np.repeat(np.arange(E), counts)
            n = env.size
            if n:
                lo, hi = cfg.hole_radius_px
                cu, cv = rng.uniform(0.0, W, n), rng.uniform(0.0, H, n)
                _paint_holes(z, env, cu, cv, rng.uniform(lo, hi, n), rng.uniform(lo, hi, n))
        return z.astype(np.float32, copy=False)
