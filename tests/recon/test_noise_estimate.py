"""The camera noise model estimated from the N-step fit residual of one fringe set."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.recon.noise import estimate_sensor_noise
from app.recon.patterns import PatternSchedule
from tests.recon.analytic_rig import Rig, bump_surface


@pytest.mark.parametrize("steps", [4, 6])
def test_estimate_recovers_shot_and_read_noise(steps):
    rig = Rig(width=320, height=240, focal_px=400.0, schedule=PatternSchedule(steps=steps))
    clean = rig.render(bump_surface(rig), background=600.0, amplitude=300.0, dtype=np.uint16).astype(np.float64)
    # albedo varies across the image so intensities span a wide range
    albedo = np.linspace(0.2, 1.0, rig.width)[None, None, :]
    mean = clean * albedo
    gain, read = 0.5, 4.0
    rng = np.random.default_rng(3)
    frames = np.rint(mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)).astype(np.uint16)
    est = estimate_sensor_noise(frames, rig.schedule)
    assert est.gain_dn_per_e == pytest.approx(gain, rel=0.05)
    assert est.read_noise_dn == pytest.approx(math.sqrt(read**2 + 1 / 12), rel=0.15)


def test_estimate_needs_more_than_three_steps():
    rig = Rig(schedule=PatternSchedule(steps=3))
    frames = rig.render(bump_surface(rig))
    with pytest.raises(ValueError, match="N > 3"):
        estimate_sensor_noise(frames, rig.schedule)
