"""Depth camera: exact batched ray casting, sensor model, point clouds, normalisation and PNG helpers.

See ``docs/depth.md`` for the camera model, frames, the sensor model and benchmark figures.
"""

from envs.camera.config import CameraConfig, DepthNoiseConfig
from envs.camera.model import R_bc, camera_poses, intrinsics, min_pool, normalize_depth, ray_dirs_c, ray_grid
from envs.camera.noise import DepthNoise
from envs.camera.pointcloud import depth_to_points, key_slots, voxel_downsample, voxel_keys
from envs.camera.renderer import DepthCamera
from envs.camera.viz import depth_to_rgb, save_depth_png, save_depth_strip

__all__ = [
    "CameraConfig",
    "DepthCamera",
    "DepthNoise",
    "DepthNoiseConfig",
    "R_bc",
    "camera_poses",
    "depth_to_points",
    "depth_to_rgb",
    "intrinsics",
    "min_pool",
    "normalize_depth",
    "ray_dirs_c",
    "ray_grid",
    "save_depth_png",
    "save_depth_strip",
    "key_slots",
    "voxel_downsample",
    "voxel_keys",
]
