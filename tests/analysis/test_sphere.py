"""Sphere fit and VDI/VDE 2634-2 PF/PS against known spheres."""

from __future__ import annotations

import numpy as np
import pytest

from app.analysis import fit_sphere, sphere_figures


def _cap(radius=5.0, center=(1.0, -2.0, 70.0), n=4000, sigma=0.0, seed=0):
    """Points on the camera-facing half of a sphere, radial noise σ."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = -np.abs(d[:, 2])
    r = radius + rng.normal(0, sigma, n)
    return np.asarray(center) + d * r[:, None]


def test_exact_sphere():
    fit = fit_sphere(_cap())
    np.testing.assert_allclose(fit.center, [1.0, -2.0, 70.0], atol=1e-9)
    assert fit.radius_mm == pytest.approx(5.0, abs=1e-9)
    figs = sphere_figures(_cap(), 10.0)
    assert figs.ps_mm == pytest.approx(0.0, abs=1e-9) and figs.pf_mm < 1e-9


def test_noisy_sphere_size_and_form():
    sigma = 0.02
    pts = _cap(sigma=sigma, n=20000)
    figs = sphere_figures(pts, 10.0, segment=False)
    assert abs(figs.ps_mm) < 0.002
    assert figs.rms_mm == pytest.approx(sigma, rel=0.05)
    # Range of 20 000 normals with 0.3 % excluded ≈ 2·2.97σ.
    assert 5.0 * sigma < figs.pf_mm < 7.0 * sigma


def test_sphere_found_among_background_plane():
    sphere = _cap(sigma=0.01, n=5000)
    rng = np.random.default_rng(2)
    plane = np.stack(
        [rng.uniform(-15, 15, 8000), rng.uniform(-15, 15, 8000), np.full(8000, 75.0)], axis=1
    )
    plane = plane[np.linalg.norm(plane[:, :2] - [1.0, -2.0], axis=1) > 5.5]
    figs = sphere_figures(np.concatenate([sphere, plane]), 10.0)
    assert abs(figs.ps_mm) < 0.005
    assert figs.n_points == pytest.approx(len(sphere), rel=0.02)


def test_sphere_arguments():
    with pytest.raises(ValueError, match="^diameter_mm"):
        sphere_figures(_cap(), -1.0)
    with pytest.raises(ValueError, match="^points"):
        fit_sphere(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="^points"):
        fit_sphere(np.c_[np.random.default_rng(0).normal(size=(50, 2)), np.zeros(50)])
