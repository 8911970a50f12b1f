"""Acceptance helpers against analytic geometry."""

from __future__ import annotations

import numpy as np
import pytest

from app.analysis.acceptance import projector_incidence_cos


def _unit_sphere_points(theta: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)


def test_incidence_on_a_unit_sphere_lit_from_the_axis():
    d = 4.0  # projector on the +z axis, 4 radii from the centre
    theta = np.linspace(0.0, np.pi, 181)
    p = _unit_sphere_points(theta)
    got = projector_incidence_cos(p, p, [0.0, 0.0, d])
    want = (d * np.cos(theta) - 1.0) / np.sqrt(1.0 + d * d - 2.0 * d * np.cos(theta))
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert got[0] == pytest.approx(1.0)
    # the shadow line: the projector's rays touch the sphere where cos θ = 1/d
    assert np.all((got > 0) == (np.cos(theta) > 1.0 / d + 1e-12))


def test_lit_fraction_of_a_uniformly_sampled_sphere():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(200_000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = 5.0
    lit = projector_incidence_cos(n, n, [0.0, 0.0, d]) > 0
    assert lit.mean() == pytest.approx((1 - 1 / d) / 2, abs=0.005)  # spherical cap area


def test_bad_input_names_the_argument():
    p = np.zeros((4, 3))
    with pytest.raises(ValueError, match="normals"):
        projector_incidence_cos(p, np.zeros((4, 2)), [0, 0, 1])
    with pytest.raises(ValueError, match="projector_centre_mm"):
        projector_incidence_cos(p, p, [0, np.nan, 1])


def _fake_result(depth, valid, reason=None):
    from types import SimpleNamespace

    r = np.zeros(depth.shape, np.uint8) if reason is None else reason
    return SimpleNamespace(depth=np.where(valid, depth, np.nan), valid=valid, reason=r)


def test_ninths_on_a_constructed_case():
    from app.analysis.acceptance import ninths_report

    rng = np.random.default_rng(0)
    h, w = 90, 120
    truth = np.tile(np.linspace(-2.0, 22.0, w), (h, 1))  # left columns below the volume
    sigma = np.full((h, w), 0.02)
    noise = rng.normal(0.0, 0.02, (h, w))
    depth = truth + noise
    depth[:30, 80:] += 0.3  # top-right ninth biased
    depth[60:, 40:80][::10, ::10] += 1.0  # bottom-centre ninth: 3 × 4 gross pixels
    valid = np.ones((h, w), bool)
    valid[30:60, :40][:, ::2] = False  # middle-left ninth: half invalid
    reason = np.zeros((h, w), np.uint8)
    reason[30:60, :40][:, ::2] = 2  # … because saturated: excluded from its valid fraction
    cells = ninths_report(_fake_result(depth, valid, reason), truth, (0.0, 20.0), sigma)
    assert [(c["row"], c["col"]) for c in cells] == [(r, c) for r in range(3) for c in range(3)]
    top_right, mid_left, bottom_mid = cells[2], cells[3], cells[7]
    assert top_right["mean_error_mm"] == pytest.approx(0.3, abs=0.005)
    assert top_right["rms_ratio"] == pytest.approx(np.hypot(0.3, 0.02) / 0.02, rel=0.02)
    assert top_right["std_ratio"] == pytest.approx(1.0, abs=0.1)
    assert cells[4]["rms_ratio"] == pytest.approx(1.0, abs=0.1) and cells[4]["gross"] == 0
    assert mid_left["valid_fraction"] == 1.0  # the invalid ones were saturated
    assert bottom_mid["gross"] == 12
    cols_out = truth[0] < 0.0  # columns below the volume: all in the left third
    assert (
        cells[0]["outside_pixels"] == 30 * int(cols_out.sum()) and cells[1]["outside_pixels"] == 0
    )
    assert (
        cells[0]["outside_valid"] == cells[0]["outside_pixels"] and cells[0]["outside_gross"] == 0
    )
    lit = np.zeros((h, w), bool)
    empty = ninths_report(_fake_result(depth, valid), truth, (0.0, 20.0), sigma, lit=lit)
    assert all(c["pixels"] == 0 and np.isnan(c["valid_fraction"]) for c in empty)
    with pytest.raises(ValueError, match="sigma_mm"):
        ninths_report(_fake_result(depth, valid), truth, (0.0, 20.0), sigma[:10])
    with pytest.raises(ValueError, match="height_range_mm"):
        ninths_report(_fake_result(depth, valid), truth, (5.0, 1.0), sigma)


def test_ninths_count_only_the_supported_region_as_inside():
    """Pixels outside the supported region leave the "inside" figures and are reported apart."""
    from app.analysis.acceptance import ninths_report, supported_mask, true_phase_rad
    from app.core.depth_model import SupportedRegion
    from app.core.schedule import PatternSchedule

    h, w = 90, 120
    truth = np.full((h, w), 5.0)
    schedule = PatternSchedule()
    k, length = schedule.frequencies[-1], schedule.axis_length
    xp = np.tile(np.linspace(0.0, length - 1.0, w), (h, 1))  # projector column grows with u
    phase = true_phase_rad(xp, schedule)
    np.testing.assert_allclose(phase, 2 * np.pi * k * xp / length)
    hi = float(phase[0, 99])  # the region ends at image column 99 (in the right third)
    region = SupportedRegion(phase_rad=(-1.0, hi))
    sup = supported_mask(region, truth, phase)
    assert sup[:, :100].all() and not sup[:, 100:].any()
    depth = truth + 0.01
    valid = np.ones((h, w), bool)
    valid[:, 100:] = False  # the reconstruction refuses the unsupported columns …
    valid[:30, 110] = True  # … but for one column of the top right ninth,
    depth[:30, 110] += 0.7  # which is wrong by more than 0.5 mm
    res = _fake_result(depth, valid)
    plain = ninths_report(res, truth, (0.0, 20.0), np.full((h, w), 0.01))
    assert plain[2]["valid_fraction"] < 0.99 and plain[2]["off_region_pixels"] == 0
    cells = ninths_report(res, truth, (0.0, 20.0), np.full((h, w), 0.01), supported=sup)
    for c in cells[2::3]:  # the right column of ninths
        assert c["pixels"] == 30 * 20 and c["valid_fraction"] == 1.0
        assert c["off_region_pixels"] == 30 * 20
    assert cells[2]["off_region_valid"] == 30 and cells[2]["off_region_gross"] == 30
    assert cells[2]["off_region_max_abs_error_mm"] == pytest.approx(0.71)
    assert cells[5]["off_region_valid"] == 0 and np.isnan(cells[5]["off_region_max_abs_error_mm"])
    assert cells[0]["off_region_pixels"] == 0 and cells[0]["pixels"] == 30 * 40
    with pytest.raises(ValueError, match="supported"):
        ninths_report(res, truth, (0.0, 20.0), np.full((h, w), 0.01), supported=sup[:, :10])
    with pytest.raises(ValueError, match="phase_rad"):
        supported_mask(region, truth, phase[:, :10])


def test_a_ninth_may_be_biased_by_twice_its_calibration_sigma_where_that_is_not_small():
    """The issue's bias rule: 0.005 mm where the ninth's RMS σ_model is ≤ 2.5 µm, else 2σ_model."""
    from app.analysis.acceptance import bias_limit_mm, ninths_report

    assert bias_limit_mm(0.0) == 0.005
    assert bias_limit_mm(0.0025) == 0.005
    assert bias_limit_mm(0.004) == pytest.approx(0.008)
    assert bias_limit_mm(float("nan")) == 0.005
    h, w = 90, 120
    truth = np.full((h, w), 5.0)
    depth = truth + 0.006
    sigma = np.full((h, w), 0.02)
    model = np.full((h, w), 0.001)
    model[:, 80:] = 0.004  # the right column of ninths: the calibration knows less there
    res = _fake_result(depth, np.ones((h, w), bool))
    cells = ninths_report(res, truth, (0.0, 20.0), sigma, sigma_model_mm=model)
    assert [c["bias_limit_mm"] for c in cells] == pytest.approx([0.005, 0.005, 0.008] * 3)
    assert cells[2]["model_sigma_mm"] == pytest.approx(0.004)
    without = ninths_report(res, truth, (0.0, 20.0), sigma)
    assert all(np.isnan(c["model_sigma_mm"]) and c["bias_limit_mm"] == 0.005 for c in without)
    with pytest.raises(ValueError, match="sigma_model_mm"):
        ninths_report(res, truth, (0.0, 20.0), sigma, sigma_model_mm=model[:10])
