"""The camera noise model estimated from the N-step fit residual of one fringe set."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon.noise import estimate_sensor_noise
from app.recon.patterns import PatternSchedule


@pytest.mark.parametrize("steps", [4, 6, 12])
def test_estimate_recovers_shot_and_read_noise(steps):
    rig = Rig(width=320, height=240, focal_px=400.0, schedule=PatternSchedule(steps=steps))
    clean = rig.render(
        bump_surface(rig), background=600.0, amplitude=300.0, dtype=np.uint16
    ).astype(np.float64)
    # albedo varies across the image so intensities span a wide range
    albedo = np.linspace(0.2, 1.0, rig.width)[None, None, :]
    mean = clean * albedo
    gain, read = 0.5, 4.0
    rng = np.random.default_rng(3)
    frames = np.rint(mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)).astype(
        np.uint16
    )
    est = estimate_sensor_noise(frames, rig.schedule)
    assert est.gain_dn_per_e == pytest.approx(gain, rel=0.05)
    assert est.read_noise_dn == pytest.approx(math.sqrt(read**2 + 1 / 12), rel=0.15)


@pytest.mark.slow
def test_a_moving_scene_keeps_a_read_noise_the_motion_test_takes():
    """The twin's anastomosis at 20 ms moves during the set: the fit's read noise came out 0 and
    the live motion test refused it (no depth map); it is at least the rounding noise."""
    from app.devices.sim.offline import render_capture_set
    from app.recon.motion import motion_mask
    from app.recon.noise import QUANTISATION_NOISE_DN

    cap, _, _ = render_capture_set("anastomosis", exposure_ms=20, seed=1)
    est = estimate_sensor_noise(cap.frames, cap.schedule, max_code=cap.max_code)
    assert est.read_noise_dn >= QUANTISATION_NOISE_DN
    moved = motion_mask(cap.frames, len(cap.schedule.frequencies), noise=est, max_code=cap.max_code)
    assert moved.shape == cap.frames.shape[1:]


def test_estimate_needs_more_than_three_steps():
    rig = Rig(schedule=PatternSchedule(steps=3))
    frames = rig.render(bump_surface(rig))
    with pytest.raises(ValueError, match="N > 3"):
        estimate_sensor_noise(frames, rig.schedule)


def test_projector_gamma_harmonics_are_not_noise():
    """A gamma-distorted fringe (10–90 % of the projector range, γ = 2.2): with N = 12 the estimate
    still finds the sensor's noise."""
    rig = Rig(width=320, height=240, focal_px=400.0, schedule=PatternSchedule(steps=12))
    lin = (
        rig.render(bump_surface(rig), background=30000.0, amplitude=24000.0, dtype=np.uint16)
        / 60000.0
    )
    mean = 2000.0 * lin**2.2 * np.linspace(0.3, 1.0, rig.width)[None, None, :]
    gain, read = 0.5, 4.0
    rng = np.random.default_rng(4)
    noisy = mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)
    frames = np.clip(np.rint(noisy), 0, 65535).astype(np.uint16)
    est = estimate_sensor_noise(frames, rig.schedule)
    assert est.gain_dn_per_e == pytest.approx(gain, rel=0.1)
    # the four-step subset cannot tell the second harmonic from noise: an upper bound
    four = PatternSchedule(steps=4)
    sub = frames.reshape(4, 12, *frames.shape[1:])[:, ::3].reshape(16, *frames.shape[1:])
    assert estimate_sensor_noise(sub, four).variance_dn2(1000.0) > 2 * est.variance_dn2(1000.0)
