"""Configuration of the depth camera and of its sensor model (typed dataclasses, loaded through ``envs.config``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from envs.config import require


@dataclass
class CameraConfig:
    """Pinhole z-depth camera rigidly mounted on the vehicle body.

    Defaults follow the Intel RealSense D435(i) depth stream (datasheet: 87 x 58 degree field of view, minimum
    depth about 0.2 m at the lowest resolution) resampled to the paper's 100 x 60 image.
    """

    width: int = 100
    """Image width in pixels (u, to the right)."""
    height: int = 60
    """Image height in pixels (v, downwards)."""
    hfov_deg: float = 87.0
    """Horizontal field of view in degrees, edge to edge of the image."""
    vfov_deg: float = 58.0
    """Vertical field of view in degrees, edge to edge of the image (pixels need not be square)."""
    min_range: float = 0.2
    """Minimum z-depth in metres. Surfaces closer than this read ``min_range`` in the clean image."""
    max_range: float = 10.0
    """Maximum z-depth in metres. Pixels with no surface within it read ``max_range``."""
    mount_pos_b: list[float] = field(default_factory=lambda: [0.1, 0.0, 0.0])
    """Optical centre in the body frame (FLU: x forward, y left, z up), metres."""
    mount_pitch_deg: float = 0.0
    """Mount pitch in degrees about body +y; positive tilts the optical axis down (towards body -z)."""
    normalization: str = "inverse"
    """Network input mapping (see ``normalize_depth``): ``inverse`` (min_range / z) or ``linear`` (z / max_range)."""

    def validate(self, prefix: str = "") -> None:
        """Raise ``ConfigError`` naming the dotted key of the first invalid field."""
        require(self.width >= 1, f"{prefix}width", f"must be >= 1, got {self.width}")
        require(self.height >= 1, f"{prefix}height", f"must be >= 1, got {self.height}")
        require(0.0 < self.hfov_deg < 180.0, f"{prefix}hfov_deg", f"must be in (0, 180), got {self.hfov_deg}")
        require(0.0 < self.vfov_deg < 180.0, f"{prefix}vfov_deg", f"must be in (0, 180), got {self.vfov_deg}")
        require(
            math.isfinite(self.min_range) and self.min_range > 0.0,
            f"{prefix}min_range",
            f"must be a positive number, got {self.min_range}",
        )
        require(
            math.isfinite(self.max_range) and self.max_range > self.min_range,
            f"{prefix}max_range",
            f"must be finite and > min_range ({self.min_range}), got {self.max_range}",
        )
        require(
            len(self.mount_pos_b) == 3 and all(math.isfinite(float(v)) for v in self.mount_pos_b),
            f"{prefix}mount_pos_b",
            f"must be 3 finite numbers, got {self.mount_pos_b}",
        )
        require(
            -90.0 <= self.mount_pitch_deg <= 90.0,
            f"{prefix}mount_pitch_deg",
            f"must be in [-90, 90], got {self.mount_pitch_deg}",
        )
        require(
            self.normalization in ("inverse", "linear"),
            f"{prefix}normalization",
            f"must be 'inverse' or 'linear', got {self.normalization!r}",
        )


@dataclass
class DepthNoiseConfig:
    """Sensor model applied to clean depth images for domain randomization. Every effect is off by default.

    Invalid pixels (dropout, holes, too close) read 0, as a RealSense reports them.
    """

    depth_sigma_coeff: float = 0.0
    """Gaussian noise std per squared metre (1/m): ``sigma(z) = coeff * z**2`` (stereo error grows with z^2).
    0.01 gives 0.04 m at 2 m, the D435 datasheet's "< 2% at 2 m" depth error."""
    dropout_prob: float = 0.0
    """Probability that any pixel independently reads 0 (invalid) in a frame."""
    holes_per_frame: float = 0.0
    """Mean number (Poisson) of elliptical invalid holes per frame."""
    hole_radius_px: list[float] = field(default_factory=lambda: [2.0, 8.0])
    """Range [lo, hi] of hole semi-axes in pixels, sampled uniformly per hole and axis."""
    edge_prob: float = 0.0
    """Probability that a pixel on a depth edge becomes a flying pixel (depth uniform between its own value
    and the farther 4-neighbour's)."""
    edge_threshold: float = 0.1
    """A pixel is on an edge when a 4-neighbour's depth differs by more than this fraction of its own depth."""
    invalid_below_min: bool = False
    """If true, pixels at or below the camera's ``min_range`` read 0 (too close for stereo), as on a D435."""
    frame_rate_hz: float = 0.0
    """Camera frame rate in Hz; 0 means a new frame every control step. Between frames the last frame is held."""
    random_phase: bool = True
    """With a frame rate set, start each env's frame clock at a random phase on reset (envs not in lockstep)."""
    latency_frames: int = 0
    """Whole frames of latency: the output is the frame captured this many frames ago."""

    def validate(self, prefix: str = "") -> None:
        """Raise ``ConfigError`` naming the dotted key of the first invalid field."""
        require(self.depth_sigma_coeff >= 0.0, f"{prefix}depth_sigma_coeff", "must be >= 0")
        require(0.0 <= self.dropout_prob <= 1.0, f"{prefix}dropout_prob", "must be in [0, 1]")
        require(self.holes_per_frame >= 0.0, f"{prefix}holes_per_frame", "must be >= 0")
        require(
            len(self.hole_radius_px) == 2 and 0.0 < self.hole_radius_px[0] <= self.hole_radius_px[1],
            f"{prefix}hole_radius_px",
            f"must be [lo, hi] with 0 < lo <= hi, got {self.hole_radius_px}",
        )
        require(0.0 <= self.edge_prob <= 1.0, f"{prefix}edge_prob", "must be in [0, 1]")
        require(self.edge_threshold > 0.0, f"{prefix}edge_threshold", "must be > 0")
        require(self.frame_rate_hz >= 0.0, f"{prefix}frame_rate_hz", "must be >= 0")
        require(self.latency_frames >= 0, f"{prefix}latency_frames", "must be >= 0")
