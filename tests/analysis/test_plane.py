"""Plane accuracy/precision/flatness against planes with known noise and bias."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.analysis import fit_plane_mlesac, plane_accuracy


def _incline(h=240, w=320, sigma=0.0, bias=None, seed=0):
    """(H, W, 3) points of a 45° plane (rising toward the camera along x) with noise along its
    normal."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (xx - w / 2) * 0.05
    y = (yy - h / 2) * 0.05
    z = 60.0 + x  # 45°: z rises with x
    pts = np.stack([x, y, z], axis=-1)
    n = np.array([1.0, 0.0, -1.0]) / math.sqrt(2)
    off = rng.normal(0, sigma, (h, w)) if sigma else np.zeros((h, w))
    if bias is not None:
        off = off + bias(x)
    return pts + off[..., None] * n, n


def test_noise_free_plane_is_exact():
    pts, n = _incline()
    res = plane_accuracy(pts)
    assert abs(abs(res.plane.normal @ n) - 1) < 1e-9
    assert res.accuracy_mm < 1e-9 and res.precision_mm < 1e-9 and res.flatness_mm < 1e-9
    assert res.n_points == pts.shape[0] * pts.shape[1]
    assert len(res.bins) == math.ceil(math.sqrt(res.n_points))


def test_precision_equals_noise_and_flatness_spans_it():
    sigma = 0.1
    pts, n = _incline(sigma=sigma)
    res = plane_accuracy(pts)
    assert res.precision_mm == pytest.approx(sigma, rel=0.03)
    assert res.std_distance_mm == pytest.approx(sigma, rel=0.03)
    assert abs(res.mean_distance_mm) < 0.01
    # Systematic part only from bin-mean noise: ≈ σ/√(count per bin)·√(2/π).
    per_bin = res.n_points / len(res.bins)
    assert res.accuracy_mm < 2 * sigma / math.sqrt(per_bin)
    assert 5.5 * sigma < res.flatness_mm < 6.5 * sigma  # 0.3 % excluded: |d| ≤ 2.97σ, range ≈ 5.94σ
    assert math.degrees(math.acos(abs(res.plane.normal @ n))) < 0.05


def test_accuracy_sees_a_systematic_bow_along_the_incline():
    amp = 0.05
    pts, _ = _incline(bias=lambda x: amp * np.cos(2 * np.pi * x / 16.0))
    res = plane_accuracy(pts)
    # Mean |cos| over whole periods is 2/π; the plane follows the bow's mean (zero).
    assert res.accuracy_mm == pytest.approx(amp * 2 / np.pi, rel=0.05)
    assert res.precision_mm < 0.2 * amp
    centers = np.array([b.center_mm for b in res.bins])
    means = np.array([b.accuracy_mm for b in res.bins])
    x = (centers * math.sqrt(2) - 60.0) / 2  # bins run along (1, 0, 1)/√2 on z = 60 + x
    assert np.corrcoef(means, amp * np.cos(2 * np.pi * x / 16.0))[0, 1] > 0.95


def test_mlesac_ignores_outliers_and_roi_selects():
    pts, n = _incline(sigma=0.02)
    rng = np.random.default_rng(1)
    flat = pts.reshape(-1, 3).copy()
    bad = rng.choice(len(flat), len(flat) // 5, replace=False)
    flat[bad, 2] += rng.uniform(0.5, 3.0, len(bad))  # 20 % gross outliers above the plane
    fit = fit_plane_mlesac(flat)
    assert math.degrees(math.acos(abs(fit.normal @ n))) < 0.1
    assert abs(np.median(fit.distances_mm(np.delete(flat, bad, axis=0)))) < 0.005
    res = plane_accuracy(pts, roi=(10, 20, 110, 70))
    assert res.n_points == 100 * 50
    valid = np.zeros(pts.shape[:2], bool)
    valid[:, :50] = True
    assert plane_accuracy(pts, valid).n_points == pts.shape[0] * 50


def test_bad_arguments_name_themselves():
    pts, _ = _incline(h=20, w=20)
    with pytest.raises(ValueError, match="^points"):
        plane_accuracy(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="^roi"):
        plane_accuracy(pts, roi=(0, 0, 50, 5))
    with pytest.raises(ValueError, match="^valid"):
        plane_accuracy(pts, np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="^inlier_mm"):
        fit_plane_mlesac(pts.reshape(-1, 3), inlier_mm=0)
