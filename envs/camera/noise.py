"""Sensor model for domain randomization: stereo noise, invalid pixels, flying pixels, frame rate and latency."""

from __future__ import annotations

import numba as nb
import numpy as np

from envs.camera.config import CameraConfig, DepthNoiseConfig


@nb.njit(cache=True, fastmath=False, nogil=True)
def _paint_holes(img: np.ndarray, holes: np.ndarray) -> None:
    """Zero the pixels of ``img`` (H, W) inside the ellipses ``holes`` (K, 4): centre (u, v), semi-axes (u, v)."""
    H, W = img.shape
    cu, cv, au, av = holes[:, 0], holes[:, 1], holes[:, 2], holes[:, 3]
    for k in range(holes.shape[0]):
        v0, v1 = max(int(np.floor(cv[k] - av[k])), 0), min(int(np.ceil(cv[k] + av[k])), H - 1)
        u0, u1 = max(int(np.floor(cu[k] - au[k])), 0), min(int(np.ceil(cu[k] + au[k])), W - 1)
        for v in range(v0, v1 + 1):
            dv = (v + 0.5 - cv[k]) / av[k]
            for u in range(u0, u1 + 1):
                du = (u + 0.5 - cu[k]) / au[k]
                if du * du + dv * dv <= 1.0:  # pixel centre inside the ellipse
                    img[v, u] = 0.0


@nb.njit(cache=True, fastmath=False, nogil=True)
def _corrupt_pixels(
    clean: np.ndarray,
    out: np.ndarray,
    rng: np.random.Generator,
    edge_prob: float,
    edge_thr: float,
    sigma_k: float,
    zmin: float,
    zmax: float,
    invalid_below: bool,
    dropout: float,
) -> None:
    """Steps 1-4 of ``DepthNoise`` on one frame (H, W): flying pixels, stereo noise, too-close invalid, dropout."""
    H, W = clean.shape
    if True:  # keeps the indentation of the per-pixel body readable
        for v in range(H):
            for u in range(W):
                z = clean[v, u]
                if edge_prob > 0.0:
                    # the most different 4-neighbour (border pixels: missing neighbours are skipped)
                    jump = 0.0
                    if v > 0 and abs(clean[v - 1, u] - z) > abs(jump):
                        jump = clean[v - 1, u] - z
                    if v < H - 1 and abs(clean[v + 1, u] - z) > abs(jump):
                        jump = clean[v + 1, u] - z
                    if u > 0 and abs(clean[v, u - 1] - z) > abs(jump):
                        jump = clean[v, u - 1] - z
                    if u < W - 1 and abs(clean[v, u + 1] - z) > abs(jump):
                        jump = clean[v, u + 1] - z
                    if abs(jump) > edge_thr * z and rng.random() < edge_prob:
                        z = z + rng.random() * jump  # flying pixel between the two surfaces
                if sigma_k > 0.0 and z < zmax:
                    # stereo: sigma_z = z^2 * sigma_disparity / (f * baseline) = sigma_k * z^2
                    z = z + sigma_k * z * z * rng.standard_normal()
                    z = min(max(z, zmin), zmax)
                if invalid_below and z <= zmin:
                    z = 0.0
                if dropout > 0.0 and rng.random() < dropout:
                    z = 0.0
                out[v, u] = z


@nb.njit(cache=True, fastmath=False, nogil=True)
def _capture(
    clean: np.ndarray,
    ids: np.ndarray,
    fresh: np.ndarray,
    line: np.ndarray,
    head: np.ndarray,
    out: np.ndarray,
    holes: np.ndarray,
    hole_ptr: np.ndarray,
    rng: np.random.Generator,
    edge_prob: float,
    edge_thr: float,
    sigma_k: float,
    zmin: float,
    zmax: float,
    invalid_below: bool,
    dropout: float,
) -> None:
    """Corrupt ``clean[e, 0]`` for each env e in ``ids`` into its latency line, then show the line's oldest frame.

    ``line`` (N, L, H, W) is a ring per env; ``head[e]`` is the slot written next (the oldest frame). A fresh
    env's frame fills all L slots. Env ``ids[k]`` gets the holes ``holes[hole_ptr[k]:hole_ptr[k + 1]]``.
    """
    L = line.shape[1]
    for k in range(ids.shape[0]):
        e = ids[k]
        slot = 0 if fresh[k] else head[e]
        frame = line[e, slot]
        _corrupt_pixels(clean[e, 0], frame, rng, edge_prob, edge_thr, sigma_k, zmin, zmax, invalid_below, dropout)
        _paint_holes(frame, holes[hole_ptr[k] : hole_ptr[k + 1]])
        if fresh[k]:
            for j in range(1, L):
                line[e, j] = frame
            head[e] = 0
        else:
            head[e] = (slot + 1) % L
        out[e, 0] = line[e, head[e]]


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
        clean = np.ascontiguousarray(clean, dtype=np.float32)
        if clean.shape != self._out_buf.shape:
            raise ValueError(f"clean depth must have shape {self._out_buf.shape}, got {clean.shape}")
        due = self.due()
        ids = np.flatnonzero(due)
        if ids.size:
            cfg, cam = self.cfg, self.cam_cfg
            fresh = self._fresh_buf[ids]
            H, W = cam.height, cam.width
            if cfg.holes_per_frame > 0.0:
                counts = rng.poisson(cfg.holes_per_frame, size=ids.size)
                n = int(counts.sum())
                lo, hi = cfg.hole_radius_px
                holes = np.stack(
                    [rng.uniform(0.0, W, n), rng.uniform(0.0, H, n), rng.uniform(lo, hi, n), rng.uniform(lo, hi, n)], 1
                )
            else:
                counts, holes = np.zeros(ids.size, dtype=np.int64), np.zeros((0, 4))
            hole_ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            # Ranges as the float32 values the clean image holds (a pixel clamped to 0.2 m reads 0.2f > 0.2).
            zlo, zhi = float(np.float32(cam.min_range)), float(np.float32(cam.max_range))
            _capture(
                clean, ids, fresh, self._line_buf, self._head_buf, self._out_buf, holes, hole_ptr, rng,
                cfg.edge_prob, cfg.edge_threshold, cfg.depth_sigma_coeff, zlo, zhi,
                cfg.invalid_below_min, cfg.dropout_prob,
            )  # fmt: skip
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
