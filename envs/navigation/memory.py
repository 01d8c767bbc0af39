"""Onboard memory of the scene from the policy's own depth frames: bearing sectors of the nearest remembered obstacle.

See :class:`envs.navigation.config.SceneMemoryConfig` for what is kept and how it is read. Everything is vectorised
over the envs: a stored frame adds ``C`` points per env (``C`` sampled image columns), a ring keeps ``frames`` of them
per env, and the read-out is one scatter-min over the remembered points.
"""

from __future__ import annotations

import math

import numpy as np

from envs.camera.config import CameraConfig
from envs.camera.model import R_bc, ray_grid
from envs.navigation.config import SceneMemoryConfig


class SceneMemory:
    """Per-env ring of remembered obstacle points (horizontal, in the scene frame) and their sector read-out."""

    def __init__(self, cfg: SceneMemoryConfig, camera: CameraConfig, num_envs: int) -> None:  # noqa: D107
        self.cfg = cfg
        self.num_envs = num_envs
        x_u, y_v = ray_grid(camera)
        s = cfg.pixel_stride
        self.rows = np.arange(s // 2, camera.height, s)
        self.cols = np.arange(s // 2, camera.width, s)
        # Body-frame ray of each sampled pixel for unit optical depth: R_bc (x_u, y_v, 1), shape (R, C, 3).
        rays_c = np.stack(np.broadcast_arrays(x_u[self.cols][None, :], y_v[self.rows][:, None], 1.0), axis=-1)
        self._rays_b = rays_c @ R_bc(camera).T
        self._mount_b = np.asarray(camera.mount_pos_b, dtype=np.float64)
        self._max_range = float(camera.max_range)
        n, c = num_envs, len(self.cols)
        self.points = np.zeros((n, cfg.frames, c, 2))
        """Remembered horizontal points (N, frames, C, 2) in the scene frame [m]."""
        self.valid = np.zeros((n, cfg.frames, c), dtype=bool)
        """Which of them hold a point."""
        self._head = np.zeros(n, dtype=np.int64)  # next ring slot of each env
        self._since = np.full(n, cfg.interval, dtype=np.int64)  # control steps since each env stored a frame

    @property
    def dim(self) -> int:
        """Size of the observation (``bins``)."""
        return self.cfg.bins

    def reset(self, env_ids: np.ndarray) -> None:
        """Forget everything the envs ``env_ids`` remember (a new episode)."""
        self.valid[env_ids] = False
        self._since[env_ids] = self.cfg.interval  # the first frame of an episode is stored

    def push(self, depth: np.ndarray, pos: np.ndarray, r_wb: np.ndarray, captured: np.ndarray) -> None:
        """Advance one control step and store the frames due.

        An env's new frame is stored when it ``captured`` one at least ``interval`` steps after its last stored
        frame; it replaces that env's oldest stored frame.

        Args:
            depth: Metric depth (N, 1, H, W) or (N, H, W) as the sensor reports it (0 or >= max range: no return).
            pos: Body positions (N, 3) in the scene frame when the frames were taken.
            r_wb: Body-to-world rotations (N, 3, 3).
            captured: Bool (N,): envs whose ``depth`` row is a new frame this step.
        """
        self._since += 1
        ids = np.flatnonzero(np.asarray(captured, dtype=bool) & (self._since > self.cfg.interval))
        if ids.size == 0:
            return
        self._since[ids] = 1
        depth = np.asarray(depth)
        d = depth.reshape(self.num_envs, -1, depth.shape[-1])[ids]
        z = d[:, self.rows][:, :, self.cols].astype(np.float64)  # (M, R, C)
        rot, p = r_wb[ids], pos[ids]
        dirs = np.einsum("mij,rcj->mrci", rot, self._rays_b)  # (M, R, C, 3)
        origin = p + rot @ self._mount_b  # (M, 3)
        pts = origin[:, None, None, :] + z[..., None] * dirs  # (M, R, C, 3)
        ok = (z > 0.0) & (z < self._max_range) & (np.abs(pts[..., 2] - p[:, None, None, 2]) <= self.cfg.band)
        dist = np.where(ok, np.linalg.norm(pts[..., :2] - p[:, None, None, :2], axis=-1), np.inf)
        best = np.argmin(dist, axis=1)  # (M, C): nearest in-band row of each column
        take = np.take_along_axis
        slot = self._head[ids]
        self.points[ids, slot] = take(pts[..., :2], best[:, None, :, None], axis=1)[:, 0]
        self.valid[ids, slot] = take(ok, best[:, None, :], axis=1)[:, 0]
        self._head[ids] = (slot + 1) % self.cfg.frames

    def observe(self, pos: np.ndarray, r_wb: np.ndarray) -> np.ndarray:
        """Sector read-out (N, bins) float32 in (0, 1]: nearest remembered horizontal distance / range, clipped to 1."""
        cfg = self.cfg
        n = self.num_envs
        env, frame, col = np.nonzero(self.valid)
        rel = self.points[env, frame, col] - pos[env, :2]  # (P, 2)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        psi = np.arctan2(r_wb[:, 1, 0], r_wb[:, 0, 0])
        bearing = np.arctan2(rel[:, 1], rel[:, 0]) - psi[env]
        sector = np.floor((bearing + math.pi) / (2.0 * math.pi) * cfg.bins).astype(np.int64) % cfg.bins
        keep = dist < cfg.range
        out = np.full(n * cfg.bins, cfg.range)
        np.minimum.at(out, (env * cfg.bins + sector)[keep], dist[keep])
        return (out.reshape(n, cfg.bins) / cfg.range).astype(np.float32)
