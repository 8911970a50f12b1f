"""Noise-floor prediction: the N-step phase noise formula checked by Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.analysis import dz_dphi, height_noise_mm, phase_noise_rad
from app.calib import fit_observations
from tests.helpers.calib_rig import BOARD, STANDARD_POSES, Rig, board_pose


def test_phase_noise_matches_monte_carlo():
    rng = np.random.default_rng(0)
    n, a, b, sigma = 4, 120.0, 60.0, 2.0
    phi = rng.uniform(-math.pi, math.pi, 200000)
    delta = 2 * math.pi * np.arange(n) / n
    frames = a + b * np.cos(phi[:, None] + delta[None, :]) + rng.normal(0, sigma, (phi.size, n))
    est = np.arctan2(-(frames * np.sin(delta)).sum(1), (frames * np.cos(delta)).sum(1))
    err = np.angle(np.exp(1j * (est - phi)))
    assert err.std() == pytest.approx(float(phase_noise_rad(sigma, b, n)), rel=0.02)
    assert np.isnan(phase_noise_rad(1.0, np.array([0.0, np.nan]), 4)).all()
    with pytest.raises(ValueError, match="^steps"):
        phase_noise_rad(1.0, 1.0, 2)


def test_height_noise_uses_model_slope():
    rig = Rig()
    obs = []
    for i, (d, ax, ay, az, sh) in enumerate(STANDARD_POSES):
        r, t = board_pose(BOARD, d, ax, ay, az, sh)
        obs.append(rig.observe(BOARD, r, t, f"pose_{i:02d}"))
    cal = fit_observations(obs, (rig.width, rig.height), rig.schedule).calibration
    phase = obs[2].phase.astype(np.float64)
    slope = dz_dphi(cal, phase)
    # Finite difference of the model across a larger step agrees with the derivative.
    from app.calib import height_mm
    vv, uu = np.mgrid[0:rig.height, 0:rig.width]
    fd = (height_mm(cal, uu, vv, phase + 0.05) - height_mm(cal, uu, vv, phase - 0.05)) / 0.1
    np.testing.assert_allclose(
        slope[200:300, 250:400], fd.reshape(slope.shape)[200:300, 250:400], rtol=1e-3
    )
    sz = height_noise_mm(cal, phase, 2.0, np.full(phase.shape, 50.0))
    np.testing.assert_allclose(sz, np.abs(slope) * 2.0 * math.sqrt(0.5) / 50.0, rtol=1e-12)
