"""Depth camera: exact batched ray casting, sensor model, point clouds, normalisation and PNG helpers.

See ``docs/depth.md`` for the camera model, frames, the sensor model and benchmark figures.
"""

from envs.camera.config import CameraConfig, DepthNoiseConfig
from envs.camera.model import R_bc, camera_poses, intrinsics, normalize_depth, ray_dirs_c, ray_grid
from envs.camera.renderer import DepthCamera

__all__ = [
    "CameraConfig",
    "DepthCamera",
    "DepthNoiseConfig",
    "R_bc",
    "camera_poses",
    "intrinsics",
    "normalize_depth",
    "ray_dirs_c",
    "ray_grid",
]
