"""Reference depth rendering with MuJoCo's ``mj_multiRay``: the ground truth for tests and the benchmark."""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from envs.camera.config import CameraConfig
from envs.camera.model import camera_poses, ray_dirs_c
from envs.mjcf import OBSTACLE_GROUP


def primitives_mjcf(prims: Sequence[object]) -> str:
    """A complete MJCF model holding only ``prims`` (each with ``to_mjcf()``) in the world body."""
    geoms = "\n".join(p.to_mjcf() for p in prims)  # type: ignore[attr-defined]
    return f'<mujoco model="prims">\n<worldbody>\n{geoms}\n</worldbody>\n</mujoco>\n'


class MjDepth:
    """z-depth images by ``mj_multiRay`` (one call per camera, single thread) against a MuJoCo model.

    Only geoms in ``OBSTACLE_GROUP`` are seen (vehicles never are). Distances along unit rays are converted to
    z-depth: the camera-frame ray ``d_c = (x_u, y_v, 1)`` has unit z, so ``z = dist / |d_c|``; misses and hits
    beyond ``max_range`` read ``max_range``, hits nearer than ``min_range`` read ``min_range``.

    Args:
        cfg: Camera model.
        model: The MuJoCo model (e.g. from ``Scene.to_mjcf()``); ``data`` is created if not given.
        data: Optional ``MjData`` (its mocap bodies define the moving obstacles' current positions).
    """

    def __init__(self, cfg: CameraConfig, model: mujoco.MjModel, data: mujoco.MjData | None = None) -> None:
        self.cfg = cfg
        self.model = model
        self.data = data if data is not None else mujoco.MjData(model)
        mujoco.mj_kinematics(self.model, self.data)
        d_c = ray_dirs_c(cfg).reshape(-1, 3)
        self._norm = np.linalg.norm(d_c, axis=1)
        self._u_c = d_c / self._norm[:, None]  # unit rays, camera frame (HW, 3)
        self._group = np.zeros(6, dtype=np.uint8)
        self._group[OBSTACLE_GROUP] = 1
        n = d_c.shape[0]
        self._dist = np.empty(n)
        self._gid = np.empty(n, dtype=np.int32)

    @classmethod
    def from_xml(cls, cfg: CameraConfig, xml: str) -> MjDepth:
        """Build from an MJCF string."""
        return cls(cfg, mujoco.MjModel.from_xml_string(xml))

    def forward(self) -> None:
        """Recompute geom poses after changing ``data.mocap_pos`` / ``qpos``."""
        mujoco.mj_kinematics(self.model, self.data)

    def render_one(self, o_w: np.ndarray, R_wc: np.ndarray) -> np.ndarray:
        """Depth (H, W) float32 of one camera at optical centre ``o_w`` (3,) with rotation ``R_wc`` (3, 3)."""
        vec = np.ascontiguousarray(self._u_c @ R_wc.T).reshape(-1)
        nray = self._dist.shape[0]
        mujoco.mj_multiRay(
            self.model, self.data, np.asarray(o_w, dtype=np.float64), vec, self._group, 1, -1,
            self._gid, self._dist, None, nray, mujoco.mjMAXVAL,
        )  # fmt: skip
        z = np.where(self._gid >= 0, self._dist / self._norm, np.inf)
        z = np.clip(z, self.cfg.min_range, self.cfg.max_range)
        return z.reshape(self.cfg.height, self.cfg.width).astype(np.float32)

    def render(self, pos_w: np.ndarray, R_wb: np.ndarray) -> np.ndarray:
        """Depth (N, 1, H, W) float32 for body poses ``pos_w`` (N, 3), ``R_wb`` (N, 3, 3)."""
        o_w, R_wc = camera_poses(self.cfg, pos_w, R_wb)
        out = np.empty((o_w.shape[0], 1, self.cfg.height, self.cfg.width), dtype=np.float32)
        for i in range(o_w.shape[0]):
            out[i, 0] = self.render_one(o_w[i], R_wc[i])
        return out
