"""The change map against analytic cases: exact Δ and σ_Δ, the null rate, a bump, the edges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.recon.change import (
    ChangeTest,
    change_from_delta,
    change_map,
    pixel_area_mm2,
    summarize,
)
from app.recon.motion import chi2_isf

H, W = 1032, 1384


def _sigma_field(rng: np.random.Generator, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    return rng.uniform(0.02, 0.1, shape).astype(np.float32)


def _bump(shape: tuple[int, int], centre: tuple[float, float], radius_px: float,
          height_mm: float) -> np.ndarray:
    """A raised-cosine bump: ``height_mm`` at the centre, 0 beyond ``radius_px``."""
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    r = np.hypot(vv - centre[0], uu - centre[1]) / radius_px
    return np.where(r < 1, 0.5 * height_mm * (1 + np.cos(math.pi * np.minimum(r, 1))), 0.0)


def test_delta_and_sigma_are_exact_and_nan_where_either_map_is_invalid():
    rng = np.random.default_rng(1)
    ref = rng.uniform(2, 20, (60, 80)).astype(np.float32)
    step = np.zeros_like(ref)
    step[20:40, 30:60] = 0.5
    cur = ref + step
    s, s_ref = _sigma_field(rng, ref.shape), _sigma_field(rng, ref.shape)
    cur[0, :10] = np.nan  # invalid now
    ref[1, :10] = np.nan  # invalid in the reference
    s[2, :10] = np.nan    # no σ: not comparable
    cm = change_map(cur, s, ref, s_ref)
    ok = np.ones(ref.shape, bool)
    ok[:3, :10] = False
    assert cm.compared == ok.sum()
    assert np.isnan(cm.delta[~ok]).all() and np.isnan(cm.sigma[~ok]).all()
    np.testing.assert_allclose(cm.delta[ok], (cur - ref)[ok], atol=1e-6)
    np.testing.assert_allclose(cm.sigma[ok], np.hypot(s, s_ref)[ok], rtol=1e-6)
    np.testing.assert_allclose(cm.significance[ok], np.abs(step[ok]) / np.hypot(s, s_ref)[ok],
                               rtol=1e-5)
    assert cm.delta.dtype == cm.sigma.dtype == np.float32 and cm.changed.dtype == bool
    # a 0.5 mm step at σ_Δ ≤ 0.14 is flagged everywhere on it, nothing far from it
    assert cm.changed[20:40, 30:60].all()
    assert not cm.changed[:, :25].any() and not cm.changed[45:].any()
    assert not cm.changed[~ok].any()


def test_a_still_scene_shows_no_changed_pixel_at_the_default_rate():
    """α = 1e-4 per map: five full-size still maps show no changed pixel at all (that any of
    them shows one has a probability of at most 5e-4)."""
    rng = np.random.default_rng(2)
    for _ in range(5):
        truth = rng.uniform(0, 20, (H, W)).astype(np.float32)
        s, s_ref = _sigma_field(rng), _sigma_field(rng)
        cur = truth + s * rng.standard_normal((H, W)).astype(np.float32)
        ref = truth + s_ref * rng.standard_normal((H, W)).astype(np.float32)
        cm = change_map(cur, s, ref, s_ref)
        assert cm.changed_pixels == 0 and cm.compared == H * W


def test_the_stated_rate_per_map_is_what_still_maps_deliver():
    """The known answer on null maps: with n pixels the single-pixel tests alone flag a map
    with probability 1 − (1 − α/(2n))ⁿ ≈ α/2 (they are independent), and the union bound caps
    all 2n tests at α. At α = 0.2, 600 still 48 × 64 maps: the share of maps with any changed
    pixel lies between (binomial 3.5 σ bands)."""
    rng = np.random.default_rng(12)
    alpha, n_maps, shape = 0.2, 600, (48, 64)
    test = ChangeTest(false_alarm_rate=alpha)
    n = shape[0] * shape[1]
    _, q1 = test.thresholds(n)
    any_flag = lone = 0
    for _ in range(n_maps):
        s, s_ref = _sigma_field(rng, shape), _sigma_field(rng, shape)
        ref = rng.uniform(0, 20, shape).astype(np.float32)
        cur = ref + (np.hypot(s, s_ref) * rng.standard_normal(shape)).astype(np.float32)
        cm = change_map(cur, s, ref, s_ref, test=test)
        any_flag += cm.changed.any()
        lone += bool((cm.significance ** 2 > q1).any())
    low = 1 - (1 - alpha / (2 * n)) ** n  # the single-pixel tests' exact share
    band = 3.5 * math.sqrt(alpha * (1 - alpha) / n_maps)
    assert abs(lone / n_maps - low) <= 3.5 * math.sqrt(low * (1 - low) / n_maps)
    assert low - band <= any_flag / n_maps <= alpha + band
    assert any_flag >= lone


def test_the_thresholds_are_the_chi_square_quantiles_at_the_rate_over_the_tests():
    n = H * W
    thr, q1 = ChangeTest(1e-4, 5).thresholds(n)
    assert q1 == pytest.approx(chi2_isf(1e-4 / (2 * n), 1), rel=1e-6)
    assert thr[25] == pytest.approx(chi2_isf(1e-4 / (2 * n), 25), rel=1e-6)
    assert thr[0] == np.inf
    thr1, q_none = ChangeTest(1e-4, 1).thresholds(n)  # one test per pixel
    assert q_none == np.inf and thr1[1] == pytest.approx(chi2_isf(1e-4 / n, 1), rel=1e-6)
    with pytest.raises(ValueError, match="n_pixels"):
        ChangeTest().thresholds(0)


def test_a_small_bump_is_found_where_its_change_exceeds_half_its_height():
    # 0.3 mm high, radius 50 px (3 mm across at 0.03 mm/px), both maps at σ = 0.045 mm
    rng = np.random.default_rng(3)
    truth = _bump((400, 500), (200, 250), 50, 0.3).astype(np.float32)
    sig = np.full(truth.shape, 0.045, np.float32)
    base = rng.uniform(5, 10, truth.shape).astype(np.float32)
    ref = base + sig * rng.standard_normal(truth.shape).astype(np.float32)
    cur = base + truth + sig * rng.standard_normal(truth.shape).astype(np.float32)
    cm = change_map(cur, sig, ref, sig)
    region = truth > 0.15
    assert cm.changed[region].mean() >= 0.9
    # at the crest Δ is within 2 σ_Δ of the truth (in 95 % of its pixels: Gaussian noise)
    crest = truth >= 0.95 * 0.3
    assert (np.abs(cm.delta - truth)[crest] <= 2 * cm.sigma[crest]).mean() >= 0.9
    far = np.ones(truth.shape, bool)
    far[130:270, 180:320] = False
    assert cm.changed[far].mean() <= 1e-4


def test_a_lone_strong_change_is_seen_and_lone_noise_is_not():
    rng = np.random.default_rng(4)
    sig = np.full((200, 200), 0.05, np.float32)
    ref = np.zeros((200, 200), np.float32)
    cur = (sig * rng.standard_normal(ref.shape)).astype(np.float32)
    cur[100, 100] = 0.5  # 7 σ_Δ in one pixel: a thread, a speck of tissue
    cm = change_map(cur, sig, ref, np.zeros_like(sig) + 1e-6)
    assert cm.changed[100, 100]
    # the pixel and the windows around it; elsewhere only the stated rate's false alarms
    near = np.zeros(ref.shape, bool)
    near[98:103, 98:103] = True
    assert cm.changed[near].sum() >= 9 and cm.changed[~near].mean() <= 1e-3


def test_change_from_delta_is_the_same_test():
    rng = np.random.default_rng(5)
    d = (0.05 * rng.standard_normal((100, 120))).astype(np.float32)
    d[40:60, 40:60] += 0.3
    s = np.full(d.shape, 0.05, np.float32)
    a = change_from_delta(d, s)
    b = change_map(d, s, np.zeros_like(d), np.zeros_like(d))
    assert np.array_equal(a.changed, b.changed) and np.array_equal(a.delta, b.delta)
    assert a.changed[45:55, 45:55].all()


def test_summary_names_the_largest_rise_and_sink_and_the_area():
    sig = np.full((50, 60), 0.02, np.float32)
    ref = np.zeros((50, 60), np.float32)
    cur = ref.copy()
    cur[10:15, 10:15] = 0.4
    cur[12, 12] = 0.6
    cur[30:35, 40:45] = -0.3
    cm = change_map(cur, sig, ref, sig)
    area = np.full(cur.shape, 0.01, np.float32)
    sm = summarize(cm, area)
    assert sm.rise_px == (12, 12) and sm.rise_mm == pytest.approx(0.6)
    assert sm.rise_sigma_mm == pytest.approx(math.hypot(0.02, 0.02), rel=1e-5)
    assert sm.sink_mm == pytest.approx(-0.3) and sm.sink_px is not None
    assert sm.changed_area_mm2 == pytest.approx(0.01 * cm.changed_pixels)
    quiet = summarize(change_map(ref, sig, ref, sig), area)
    assert quiet.rise_mm is None and quiet.sink_mm is None and quiet.changed_area_mm2 == 0


def test_pixel_area_of_a_fronto_parallel_plane_is_the_footprint_squared():
    f, z = 2000.0, 40.0
    vv, uu = np.mgrid[0:30, 0:40].astype(np.float32)
    pts = np.stack([(uu - 20) * z / f, (vv - 15) * z / f, np.full_like(uu, z)], -1)
    pts[5, 5] = np.nan
    area = pixel_area_mm2(pts)
    assert np.nanmax(np.abs(area - (z / f) ** 2)) < 1e-9 + 1e-5 * (z / f) ** 2
    assert np.isfinite(area[20:, 20:]).all()


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"depth": np.zeros(5, np.float32)}, "depth"),
    ({"sigma": np.zeros((4, 4), np.float32)}, "sigma"),
    ({"ref_depth": np.zeros((3, 5), np.float32)}, "ref_depth"),
    ({"ref_sigma": "x"}, "ref_sigma"),
])
def test_bad_arrays_are_named(kwargs, name):
    args = {k: np.zeros((3, 4), np.float32) for k in ("depth", "sigma", "ref_depth", "ref_sigma")}
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        change_map(**args)


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"false_alarm_rate": 0.0}, "false_alarm_rate"), ({"false_alarm_rate": float("nan")},
                                                      "false_alarm_rate"),
    ({"window_px": 4}, "window_px"), ({"window_px": 17}, "window_px"),
])
def test_bad_settings_are_named(kwargs, name):
    with pytest.raises(ValueError, match=name):
        ChangeTest(**kwargs)


def _reference_mask(cur, s, ref, s_ref, test):
    """The changed test in float64 numpy: window sums by a 2-D cumulative sum."""
    d = cur.astype(np.float64) - ref
    var = s.astype(np.float64) ** 2 + s_ref.astype(np.float64) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        q = d * d / var
    ok = np.isfinite(q)
    q = np.where(ok, q, 0.0)
    r = test.window_px // 2

    def box(a):
        p = np.pad(a, r + 1)[: a.shape[0] + 2 * r + 1, : a.shape[1] + 2 * r + 1]
        c = p.cumsum(0).cumsum(1)
        k = 2 * r + 1
        return c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]

    qs, ms = box(q), box(ok.astype(np.float64)).round().astype(int)
    thr, q1 = test.thresholds(cur.size)
    t = thr.astype(np.float64)[ms]
    return ok & ((qs > t) | (q > q1)), qs, t


@pytest.mark.parametrize("window_px", [1, 3, 5, 9])
def test_the_fused_kernel_is_the_test_computed_plainly(window_px):
    """The one-pass kernel against float64 numpy on maps with invalid pixels (alone and in
    blocks), a change region and a few huge changes (their s² is capped in the sums)."""
    rng = np.random.default_rng(7)
    shape = (203, 317)
    s, s_ref = _sigma_field(rng, shape), _sigma_field(rng, shape)
    ref = rng.uniform(0, 20, shape).astype(np.float32)
    cur = ref + (s * rng.standard_normal(shape)).astype(np.float32)
    cur[50:90, 100:160] += 0.25  # about 3 σ_Δ: found by the windows, some by single pixels
    cur[rng.random(shape) < 0.1] = np.nan
    ref[120:140, 10:60] = np.nan
    cur[rng.integers(0, shape[0], 30), rng.integers(0, shape[1], 30)] += 1e4  # a tool, 10 m
    test = ChangeTest(0.4, window_px)
    cm = change_map(cur, s, ref, s_ref, test=test)
    want, qs, t = _reference_mask(cur, s, ref, s_ref, test)
    near = np.abs(qs - t) <= 1e-4 * t  # float32 against float64 at the threshold
    assert cm.compared == int(np.isfinite(cur - ref).sum())
    assert np.array_equal(cm.changed[~near], want[~near])
    assert want.sum() > 100  # the comparison is not an empty one


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], std_mm: float,
                  scale_px: float) -> np.ndarray:
    """A smooth random error field of 1-σ ``std_mm`` varying over ``scale_px``."""
    import cv2

    f = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), scale_px)
    return (f * (std_mm / f.std())).astype(np.float32)


def test_a_shared_error_is_no_change_where_it_is_stated_and_a_bump_is_still_found():
    """Δ = a smooth error (1-σ g = 0.15 mm, three times the noise, over ~60 px: the two
    calibrations' after a scope motion) + noise. Stated as independent noise the window test
    flags much of it; stated as shared, nothing; a 0.3 mm bump on a small one is found."""
    from app.recon.change import change_with_shared_error

    rng = np.random.default_rng(21)
    shape = (400, 500)
    sig = np.full(shape, 0.05, np.float32)
    g = np.full(shape, 0.15, np.float32)
    still_shared, still_independent = [], []
    for _ in range(4):
        d = _smooth_field(rng, shape, 0.15, 20.0) + sig * rng.standard_normal(shape).astype(
            np.float32)
        still_shared.append(change_with_shared_error(d, sig, g).changed_share)
        still_independent.append(change_from_delta(d, np.hypot(sig, g)).changed_share)
    print(f"\nshared error stated: {max(still_shared):.2e} changed; as independent noise: "
          f"{min(still_independent):.2e}")
    assert max(still_shared) == 0.0
    assert min(still_independent) > 1e-3  # the reason for the shared form
    bump = _bump((400, 500), (200, 250), 50, 0.3).astype(np.float32)
    # a shared error of 0.01 mm leaves it found; one of 0.05 mm would hide it (a smooth error
    # that size makes a 0.15 mm offset a 3 σ event over a window: measured 0.3 % found)
    d = (_smooth_field(rng, shape, 0.01, 20.0) + bump
         + sig * rng.standard_normal(shape).astype(np.float32))
    cm = change_with_shared_error(d, sig, np.full(shape, 0.01, np.float32))
    np.testing.assert_allclose(cm.sigma, np.hypot(0.05, 0.01), rtol=1e-6)
    assert cm.changed[bump > 0.15].mean() >= 0.9


def test_without_a_shared_error_it_is_the_fixed_scope_test():
    from app.recon.change import change_with_shared_error

    rng = np.random.default_rng(22)
    shape = (203, 317)
    d = (0.05 * rng.standard_normal(shape)).astype(np.float32)
    d[50:90, 100:160] += 0.2
    d[rng.random(shape) < 0.05] = np.nan
    s = _sigma_field(rng, shape)
    test = ChangeTest(0.4, 5)
    a = change_with_shared_error(d, s, np.zeros(shape, np.float32), test=test)
    b = change_from_delta(d, s, test=test)
    _, qs, t = _reference_mask(d, s, np.zeros_like(d), np.zeros_like(d), test)
    near = np.abs(qs - t) <= 1e-4 * t
    assert np.array_equal(a.changed[~near], b.changed[~near]) and a.compared == b.compared
    assert b.changed.sum() > 100
    with pytest.raises(ValueError, match="shared"):
        change_with_shared_error(d, s, -np.ones(shape, np.float32))


def _summary_plainly(cm, area):
    """The summary in numpy over the whole map (the form the compiled pass replaced)."""
    ch = cm.changed
    a = area[ch]
    fill = float(np.nanmedian(area))
    total = float(np.where(np.isfinite(a), a, fill).sum())
    with np.errstate(invalid="ignore"):
        own = ch & (np.abs(cm.delta) >= 2.0 * cm.sigma)
    d = np.where(own, cm.delta, np.nan)
    rise = sink = None
    if own.any() and np.nanmax(d) > 0:
        rise = tuple(int(x) for x in np.unravel_index(int(np.nanargmax(d)), d.shape))
    if own.any() and np.nanmin(d) < 0:
        sink = tuple(int(x) for x in np.unravel_index(int(np.nanargmin(d)), d.shape))
    return total, rise, sink


def test_the_summary_is_the_plain_numpy_one():
    rng = np.random.default_rng(31)
    shape = (300, 400)
    s = _sigma_field(rng, shape)
    ref = rng.uniform(0, 20, shape).astype(np.float32)
    cur = ref + (s * rng.standard_normal(shape)).astype(np.float32)
    cur[50:80, 60:120] += 0.4
    cur[200:230, 300:340] -= 0.5
    cur[rng.random(shape) < 0.05] = np.nan
    cm = change_map(cur, s, ref, s, test=ChangeTest(0.3))
    area = rng.uniform(0.01, 0.02, shape).astype(np.float32)
    area[55:60, 70:90] = np.nan  # changed pixels without an area: the median's
    sm = summarize(cm, area)
    total, rise, sink = _summary_plainly(cm, area)
    assert sm.changed_area_mm2 == pytest.approx(total, rel=1e-5)
    assert sm.rise_px == rise and sm.sink_px == sink and rise is not None and sink is not None
    assert sm.rise_mm == pytest.approx(float(cm.delta[rise]))
    assert summarize(cm, None).changed_area_mm2 == 0.0
