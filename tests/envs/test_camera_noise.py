"""Depth sensor model: measured statistics against the configured ones, frame clock, latency, reset."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.camera import CameraConfig, DepthNoise, DepthNoiseConfig
from envs.config import ConfigError, load_config

CAM = CameraConfig()
H, W = CAM.height, CAM.width


def _flat(n, z):
    return np.full((n, 1, H, W), z, dtype=np.float32)


def test_off_by_default_is_the_identity():
    clean = np.random.default_rng(0).uniform(0.2, 10.0, (4, 1, H, W)).astype(np.float32)
    out = DepthNoise(DepthNoiseConfig(), CAM, 4).apply(clean, np.random.default_rng(1))
    assert np.array_equal(out, clean)


def test_noise_std_at_5m_is_coeff_times_z_squared():
    # sigma(5 m) = 0.01 * 5^2 = 0.25 m; 64 frames of 6000 pixels: std of the sample std ~ 0.25 / sqrt(2 * 384000)
    noise = DepthNoise(DepthNoiseConfig(depth_sigma_coeff=0.01), CAM, 64)
    out = noise.apply(_flat(64, 5.0), np.random.default_rng(2))
    err = out - 5.0
    assert err.std() == pytest.approx(0.25, rel=0.01)
    assert abs(err.mean()) < 0.003
    # and at 2 m: 0.01 * 4 = 0.04 m
    noise.reset()
    err2 = noise.apply(_flat(64, 2.0), np.random.default_rng(3)) - 2.0
    assert err2.std() == pytest.approx(0.04, rel=0.01)


def test_no_return_pixels_get_no_noise_and_output_stays_in_range():
    noise = DepthNoise(DepthNoiseConfig(depth_sigma_coeff=0.05), CAM, 8)
    clean = _flat(8, CAM.max_range)
    clean[:, :, :30] = 9.5  # sigma = 0.05 * 90 = 4.5 m: clipping matters
    out = noise.apply(clean, np.random.default_rng(4))
    assert np.all(out[:, :, 30:] == CAM.max_range)
    assert out.min() >= CAM.min_range and out.max() <= CAM.max_range


def test_dropout_fraction():
    noise = DepthNoise(DepthNoiseConfig(dropout_prob=0.1), CAM, 64)
    out = noise.apply(_flat(64, 3.0), np.random.default_rng(5))
    frac = np.mean(out == 0.0)  # binomial std sqrt(0.09 / 384000) = 0.0005
    assert frac == pytest.approx(0.1, abs=0.002)
    assert np.all(out[out != 0.0] == 3.0)


def test_hole_count_is_poisson():
    # P(no hole in a frame) = exp(-lambda); 2000 frames, lambda = 1: 0.368 +- 0.011 (1 sigma).
    noise = DepthNoise(DepthNoiseConfig(holes_per_frame=1.0, hole_radius_px=[3.0, 3.0]), CAM, 2000)
    out = noise.apply(_flat(2000, 3.0), np.random.default_rng(6))
    holes = (out == 0.0).reshape(2000, -1)
    assert np.mean(~holes.any(axis=1)) == pytest.approx(math.exp(-1.0), abs=0.04)
    # A radius-3 hole inside the image covers about pi * 9 = 28 pixel centres; holes near the border are cut
    # and overlapping holes share pixels, so the mean count per frame is a bit below lambda * 28.
    mean_zeros = holes.sum(axis=1).mean()
    assert 0.6 * math.pi * 9 < mean_zeros < 1.1 * math.pi * 9


def test_edge_pixels_fly_between_the_surfaces():
    clean = _flat(16, 6.0)
    clean[:, :, :, :50] = 2.0  # a vertical step edge between columns 49 and 50
    noise = DepthNoise(DepthNoiseConfig(edge_prob=1.0), CAM, 16)
    out = noise.apply(clean, np.random.default_rng(7))
    edge = out[:, 0, :, 49:51]
    assert np.all((edge >= 2.0) & (edge <= 6.0)) and np.mean((edge > 2.0) & (edge < 6.0)) > 0.99
    assert np.array_equal(out[:, 0, :, :49], clean[:, 0, :, :49])
    assert np.array_equal(out[:, 0, :, 51:], clean[:, 0, :, 51:])
    # With probability 0.5 per edge pixel: 64 frames x 60 rows x 2 columns, binomial std 0.01.
    half = DepthNoise(DepthNoiseConfig(edge_prob=0.5), CAM, 64)
    out = half.apply(np.repeat(clean[:1], 64, axis=0), np.random.default_rng(8))
    assert np.mean(out[:, 0, :, 49:51] != clean[:1, 0, :, 49:51]) == pytest.approx(0.5, abs=0.04)


def test_too_close_reads_invalid_when_asked():
    clean = _flat(2, 3.0)
    clean[:, :, 10:20] = CAM.min_range
    out = DepthNoise(DepthNoiseConfig(invalid_below_min=True), CAM, 2).apply(clean, np.random.default_rng(9))
    assert np.all(out[:, :, 10:20] == 0.0) and np.all(out[:, :, 20:] == 3.0)


def _stepping(noise, steps, n):
    """Feed frames whose value is the step index + 1; return outputs (steps, n) and capture masks."""
    outs, dues = [], []
    rng = np.random.default_rng(0)
    for k in range(steps):
        dues.append(noise.due())
        outs.append(noise.apply(_flat(n, k + 1.0), rng)[:, 0, 0, 0])
    return np.array(outs), np.array(dues)


def test_frame_rate_zero_order_hold():
    # 30 Hz camera, 100 Hz control: 3 s = 300 steps -> 90 frames (+1 for the capture at reset).
    noise = DepthNoise(DepthNoiseConfig(frame_rate_hz=30.0), CAM, 8, control_dt=0.01, rng=np.random.default_rng(1))
    outs, dues = _stepping(noise, 300, 8)
    counts = dues.sum(axis=0)
    assert np.all(np.abs(counts - 91) <= 1)
    for e in range(8):
        k = np.flatnonzero(dues[:, e])
        assert np.array_equal(outs[k, e], k + 1.0)  # a captured frame shows at once (no latency)
        held = ~dues[:, e]
        assert np.all(outs[held, e] == np.maximum.accumulate(np.where(dues[:, e], outs[:, e], 0))[held])
        gaps = np.diff(k)[1:]  # the first gap is the random phase after the reset
        assert set(gaps.tolist()) <= {3, 4}  # 1/30 s at 10 ms steps: 3 or 4 steps apart
    # random phases: envs do not all capture on the same steps
    assert len({tuple(np.flatnonzero(dues[:, e])[:3]) for e in range(8)}) > 1


def test_latency_in_whole_frames_and_reset():
    noise = DepthNoise(DepthNoiseConfig(latency_frames=2), CAM, 3)
    outs, _ = _stepping(noise, 6, 3)
    # step k shows frame k - 2 (values are index + 1); the first frame fills the line after a reset.
    assert np.array_equal(outs[:, 0], [1.0, 1.0, 1.0, 2.0, 3.0, 4.0])
    noise.reset([1])
    rng = np.random.default_rng(0)
    out = noise.apply(_flat(3, 50.0), rng)[:, 0, 0, 0]
    assert out[1] == 50.0  # reset env: its new frame at once, nothing from the old episode
    assert out[0] == 5.0 and out[2] == 5.0  # the others: frame from 2 steps ago
    out = noise.apply(_flat(3, 60.0), rng)[:, 0, 0, 0]
    assert out[1] == 50.0 and out[0] == 6.0


def test_noise_config_validation():
    with pytest.raises(ConfigError, match="dropout_prob"):
        load_config(DepthNoiseConfig, overrides=["dropout_prob=1.5"])
    with pytest.raises(ConfigError, match="hole_radius_px"):
        load_config(DepthNoiseConfig, overrides={"hole_radius_px": [4.0, 2.0]})
    with pytest.raises(ValueError, match="shape"):
        DepthNoise(DepthNoiseConfig(), CAM, 2).apply(_flat(3, 1.0), np.random.default_rng(0))
