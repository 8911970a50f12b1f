"""Per-pixel depth uncertainty ``ReconResult.sigma`` against Monte-Carlo scatter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.core.reasons import Reason
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor
from app.recon.reconstructor import SensorNoise

GAIN_DN_PER_E = 0.5
READ_DN = 4.0


def _noisy(clean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Shot + read noise on ``clean`` frames, rounded (the rounding adds 1/12 DN²)."""
    x = clean.astype(np.float64)
    noisy = x + rng.normal(size=x.shape) * np.sqrt(READ_DN**2 + GAIN_DN_PER_E * x)
    return np.clip(np.rint(noisy), 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("combine", [False, True])
def test_sigma_matches_monte_carlo_scatter(combine):
    rig = Rig()
    h = bump_surface(rig)
    clean = rig.render(h, background=6000.0, amplitude=3000.0, dtype=np.uint16)
    noise = SensorNoise(GAIN_DN_PER_E, math.sqrt(READ_DN**2 + 1.0 / 12.0))
    rec = Reconstructor(rig.calibration(), noise=noise, combine_frequencies=combine, max_code=65535)
    rng = np.random.default_rng(5)
    depths, sigmas = [], []
    for _ in range(300):
        res = rec.run(_noisy(clean, rng))
        depths.append(res.depth.copy())
        sigmas.append(res.sigma.copy())
    d = np.array(depths)
    ok = np.all(np.isfinite(d), axis=0)
    assert ok.mean() > 0.99
    measured = d[:, ok].std(axis=0, ddof=1)
    predicted = np.nanmean(np.array(sigmas)[:, ok], axis=0)
    ratio = measured / predicted
    assert 0.97 < np.median(ratio) < 1.03
    # 300 repeats: a per-pixel standard deviation scatters by ~4 %
    assert np.mean(np.abs(ratio - 1.0) < 0.15) > 0.99


@pytest.mark.parametrize("combine", [False, True])
def test_sigma_fast_equals_numpy(combine):
    rig = Rig()
    frames = rig.render(bump_surface(rig), noise=1.5, dtype=np.uint8)
    rec = Reconstructor(rig.calibration(), combine_frequencies=combine)
    fast, ref = rec.run(frames, fast=True), rec.run(frames, fast=False)
    assert np.array_equal(fast.valid, ref.valid)
    v = ref.valid
    assert np.all(np.isfinite(ref.sigma[v])) and np.all(np.isnan(ref.sigma[~v]))
    np.testing.assert_allclose(fast.sigma[v], ref.sigma[v], rtol=2e-3)


@pytest.mark.parametrize("fast", [False, True])
def test_max_sigma_marks_uncertain_pixels(fast):
    rig = Rig()
    frames = rig.render(bump_surface(rig), noise=1.0, dtype=np.uint8)
    base = Reconstructor(rig.calibration(), fast=fast).run(frames)
    limit = float(np.nanmedian(base.sigma))
    res = Reconstructor(rig.calibration(), fast=fast, max_sigma_mm=limit).run(frames)
    unc = res.reason == Reason.UNCERTAIN
    assert 0.3 < unc.mean() < 0.7
    assert np.array_equal(unc, base.valid & (base.sigma > limit))
    with pytest.raises(ValueError, match="max_sigma_mm"):
        Reconstructor(rig.calibration(), max_sigma_mm=-1.0)
