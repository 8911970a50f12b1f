"""Feature (suture) height against a synthetic thread of known diameter on a curved base."""

from __future__ import annotations

import numpy as np
import pytest

from app.analysis import feature_height

PX_MM = 0.04  # pixel pitch on the tissue, mm


def _scene(diameter=0.726, sigma=0.0, seed=0, angle_deg=20.0):
    """Depth: gentle quadratic tissue + a cylinder of ``diameter`` lying on it; bright thread."""
    rng = np.random.default_rng(seed)
    h, w = 200, 260
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = 5.0 + 0.01 * (xx - 130) + 0.004 * (yy - 100) + 2e-5 * (xx - 130) ** 2
    a = np.radians(angle_deg)
    # Perpendicular distance (mm) from the thread's axis line through the centre.
    t = (-(xx - 130) * np.sin(a) + (yy - 100) * np.cos(a)) * PX_MM
    along = ((xx - 130) * np.cos(a) + (yy - 100) * np.sin(a)) * PX_MM
    r = diameter / 2
    on = (np.abs(t) < r) & (np.abs(along) < 3.0)
    bump = np.where(on, r + np.sqrt(np.clip(r * r - t * t, 0, None)), 0.0)
    depth = base + bump + rng.normal(0, sigma, (h, w)) if sigma else base + bump
    texture = np.where(on, 200.0, 80.0) + rng.normal(0, 3, (h, w))
    return depth, texture, on


def test_noise_free_thread_height():
    depth, tex, on = _scene()
    res = feature_height(depth, tex)
    assert res.height_mm == pytest.approx(0.726, abs=0.005)
    assert res.height_std_mm < 0.005
    assert res.count > 100  # ≈ 6 mm / 0.04 mm cross-sections
    assert (res.mask & on).sum() / on.sum() > 0.95


def test_noisy_thread_height_and_roi():
    depth, tex, _ = _scene(sigma=0.02, seed=1)
    res = feature_height(depth, tex, roi=(40, 20, 220, 180))
    assert res.height_mm == pytest.approx(0.726, abs=0.02)
    assert 0.005 < res.height_std_mm < 0.05
    assert res.baseline_rms_mm == pytest.approx(0.02, rel=0.15)


def test_height_threshold_and_dark_polarity():
    depth, tex, _ = _scene(diameter=0.5)
    res = feature_height(depth, 255.0 - tex, polarity="dark", height_threshold_mm=0.2)
    assert res.height_mm == pytest.approx(0.5, abs=0.01)


def test_feature_arguments():
    depth, tex, _ = _scene()
    with pytest.raises(ValueError, match="^texture"):
        feature_height(depth, tex[:10])
    with pytest.raises(ValueError, match="^polarity"):
        feature_height(depth, tex, polarity="up")
    with pytest.raises(ValueError, match="^threshold"):
        feature_height(depth, tex, threshold=1e6)


def test_heavy_noise_does_not_inflate_the_crest():
    # With σ = 0.06 mm (the dark suture's noise) the apex of each section's parabola,
    # c + b²/4|a|, would read high; the value on the fitted axis must not.
    heights = [feature_height(*_scene(sigma=0.06, seed=s)[:2]).height_mm for s in range(8)]
    assert np.mean(heights) == pytest.approx(0.726, abs=0.005)  # the apex read 0.746


def _noisy(sigma, seed, dark=False, diameter=0.72, corr_px=0.0):
    """The synthetic thread with depth noise σ (white, or Gaussian-correlated over ``corr_px``)."""
    from scipy.ndimage import gaussian_filter

    depth, tex, on = _scene(diameter=diameter)
    rng = np.random.default_rng(seed)
    n = rng.normal(0.0, 1.0, depth.shape)
    if corr_px:
        n = gaussian_filter(n, corr_px)
        n /= n.std()
    return depth + sigma * n, (280.0 - tex) if dark else tex, on


@pytest.mark.parametrize("dark", [False, True], ids=["bright", "dark"])
def test_height_expectation_does_not_move_with_noise(dark):
    """Mean over seeds at each noise level equals the noise-free height (the crest is not pushed
    up)."""
    clean = feature_height(*_noisy(0.0, 0, dark)[:2]).height_mm
    assert clean == pytest.approx(0.72, abs=0.006)
    for sigma in (0.03, 0.06, 0.1):
        est = [feature_height(*_noisy(sigma, seed, dark)[:2]) for seed in range(16)]
        h = np.array([e.height_mm for e in est])
        se_mean = float(np.std(h, ddof=1) / np.sqrt(len(h)))
        # bias within 3 standard errors of the mean and within 3 µm absolute
        assert abs(h.mean() - clean) <= max(3 * se_mean, 0.003), (sigma, h.mean() - clean)
        assert all(e.polarity == ("dark" if dark else "bright") for e in est)


@pytest.mark.parametrize("corr_px", [0.0, 1.0], ids=["white", "correlated"])
def test_standard_error_matches_the_scatter(corr_px):
    """The reported standard error against the seed-to-seed scatter of the height (24 seeds: the
    ratio is known to ±15 %); measured ≈ 0.9 (white) and ≈ 0.75 (correlated) noise."""
    est = [feature_height(*_noisy(0.05, seed, corr_px=corr_px)[:2]) for seed in range(24)]
    h = np.array([e.height_mm for e in est])
    se = np.array([e.height_se_mm for e in est])
    assert np.all(np.isfinite(se)) and np.all(se > 0)
    assert 0.6 < np.median(se) / np.std(h, ddof=1) < 1.4


def test_polarity_found_or_given():
    depth, tex, _ = _noisy(0.02, 3, dark=True)
    assert feature_height(depth, tex).polarity == "dark"
    assert feature_height(depth, tex, polarity="dark").height_mm == pytest.approx(
        feature_height(depth, tex).height_mm)
    depth, tex, _ = _noisy(0.02, 3, dark=False)
    assert feature_height(depth, tex).polarity == "bright"


def _thread_on(
    base_fn, diameter=0.72, px_mm=(0.04, 0.04), angle_deg=20.0, sigma=0.0, seed=0, dark=False
):
    """A thread of ``diameter`` lying on the surface ``base_fn(along_mm, across_mm)``, imaged with
    pixel pitch ``px_mm`` (x, y) on the surface; returns depth, texture and (H, W, 2) coordinates,
    mm."""
    h, w = 220, 260
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x_mm, y_mm = (xx - 130) * px_mm[0], (yy - 110) * px_mm[1]
    a = np.radians(angle_deg)
    t = -x_mm * np.sin(a) + y_mm * np.cos(a)
    along = x_mm * np.cos(a) + y_mm * np.sin(a)
    r = diameter / 2
    on = (np.abs(t) < r) & (np.abs(along) < 3.0)
    bump = np.where(on, r + np.sqrt(np.clip(r * r - t * t, 0, None)), 0.0)
    depth = 5.0 + base_fn(along, t) + bump
    if sigma:
        depth = depth + np.random.default_rng(seed).normal(0.0, sigma, depth.shape)
    texture = np.where(on, 200.0, 80.0) + np.random.default_rng(seed + 1).normal(0, 3, depth.shape)
    return depth, (280.0 - texture) if dark else texture, np.stack([x_mm, y_mm], axis=-1)


def test_tissue_curving_under_the_thread():
    """Tissue whose curvature across the thread changes along it (folds): a line through the flanks
    misses the tissue under the crest by curvature·gap²/8; the quadratic flank fit follows it."""
    def folds(s, t):
        return 0.3 * np.cos(2 * np.pi * s / 3.0) * t * t + 0.05 * t
    depth, tex, _ = _thread_on(folds)
    quad = feature_height(depth, tex)
    line = feature_height(depth, tex, flank_degree=1)
    assert quad.height_mm == pytest.approx(0.72, abs=0.006)
    assert quad.height_std_mm < 0.01  # every section reads the same crest over its own tissue
    assert line.height_std_mm > 2 * quad.height_std_mm  # … where a line's error follows the folds


def test_section_offsets_do_not_flatten_the_profile():
    """Tissue steps along the thread (each section's crest at another height): the profile's
    curvature comes from within the sections, so it is the thread's (about 1/(2r) on the central
    part), not flattened by the section-to-section wander."""
    def steps(s, t):
        return 0.1 * np.sign(np.sin(2 * np.pi * s / 1.5)) + 0.0 * t
    depth, tex, coords = _thread_on(steps)
    res = feature_height(depth, tex, coords_mm=coords)
    assert res.height_mm == pytest.approx(0.72, abs=0.006)
    assert res.curvature_per_px2 == pytest.approx(1.0 / 0.72, rel=0.15)  # mm⁻¹ in mm coordinates


@pytest.mark.parametrize("px_mm", [(0.025, 0.025), (0.035, 0.02)], ids=["fine", "anisotropic"])
def test_metric_sections_on_other_pixel_pitches(px_mm):
    """Another camera (pitch, anisotropic foreshortening): in-plane coordinates give the thread's
    height and its true curvature; the expectation does not move with noise (dark thread)."""
    def flat(s, t):
        return 0.02 * s + 0.03 * t
    clean = feature_height(*_thread_on(flat, px_mm=px_mm, dark=True)[:2], polarity="dark",
                           coords_mm=_thread_on(flat, px_mm=px_mm)[2])
    assert clean.height_mm == pytest.approx(0.72, abs=0.006)
    assert clean.curvature_per_px2 == pytest.approx(1.0 / 0.72, rel=0.15)
    h = []
    for seed in range(8):
        depth, tex, coords = _thread_on(flat, px_mm=px_mm, sigma=0.06, seed=seed, dark=True)
        h.append(feature_height(depth, tex, coords_mm=coords).height_mm)
    se = float(np.std(h, ddof=1) / np.sqrt(len(h)))
    assert abs(np.mean(h) - clean.height_mm) <= max(3 * se, 0.004)


def test_plane_coordinates_keep_distances_on_the_plane():
    from app.analysis.feature import plane_coordinates

    rng = np.random.default_rng(2)
    n = np.array([0.2, -0.3, -0.93])
    n /= np.linalg.norm(n)
    e = np.cross(n, [1.0, 0.0, 0.0])
    e /= np.linalg.norm(e)
    f = np.cross(n, e)
    uv = rng.uniform(-10, 10, (5, 7, 2))
    pts = np.array([1.0, 2.0, 40.0]) + uv[..., :1] * e + uv[..., 1:] * f + 3.0 * n  # on a plane ⟂ n
    c = plane_coordinates(pts, n)
    d3 = np.linalg.norm(pts[0, 0] - pts, axis=-1)
    np.testing.assert_allclose(np.linalg.norm(c[0, 0] - c, axis=-1), d3, atol=1e-9)
    with pytest.raises(ValueError, match="^points"):
        plane_coordinates(pts[..., :2], n)
    with pytest.raises(ValueError, match="^normal"):
        plane_coordinates(pts, [0.0, 0.0, 0.0])
    depth, tex, coords = _thread_on(lambda s, t: 0.0 * s)
    with pytest.raises(ValueError, match="^coords_mm"):
        feature_height(depth, tex, coords_mm=coords[:10])
    with pytest.raises(ValueError, match="^flank_degree"):
        feature_height(depth, tex, flank_degree=3)


def _oblique_view(slope=0.25, view_deg=30.0, diameter=0.72, px_mm=0.03):
    """A thread lying along y on tissue sloping across it (z = slope·x), seen by an orthographic
    camera tilted by ``view_deg`` about the thread's axis: each image column looks along a slanted
    ray, so the crest's pixel sees the crest, while the tissue *under* the crest is imaged
    elsewhere (parallax ≈ height·tan(view)). Returns depth (height), texture and the visible
    points' (x, y) in the surface plane, mm, per pixel (z-buffered: the thread hides tissue)."""
    r = diameter / 2
    x = np.linspace(-3.0, 3.0, 60001)
    cap = np.where(np.abs(x) < r, r + np.sqrt(np.clip(r * r - x * x, 0, None)), 0.0)
    z = slope * x + cap
    th = np.radians(view_deg)
    u = x * np.cos(th) + z * np.sin(th)  # image coordinate across the thread
    near = -x * np.sin(th) + z * np.cos(th)  # toward the camera
    cols = np.arange(int((u.min() + 0.3) / px_mm), int((u.max() - 0.3) / px_mm))
    depth_row, x_row, on_row = [], [], []
    for c in cols:
        m = np.abs(u - c * px_mm) <= 0.02 * px_mm  # the samples on (about) this pixel's central ray
        # the ray meets the thread's side below its equator (x = −r, seen obliquely)
        if not m.any():
            depth_row.append((c * px_mm + r * np.cos(th)) / np.sin(th))
            x_row.append(-r)
            on_row.append(True)
            continue
        i = np.flatnonzero(m)[np.argmax(near[m])]  # the first surface the ray meets
        depth_row.append(z[i])
        x_row.append(x[i])
        on_row.append(abs(x[i]) < r)
    rows = 200
    depth = np.tile(np.array(depth_row), (rows, 1)) + 5.0
    xs = np.tile(np.array(x_row), (rows, 1))
    ys = np.tile(np.arange(rows, dtype=np.float64)[:, None] * px_mm, (1, len(cols)))
    on = np.tile(np.array(on_row), (rows, 1))
    texture = np.where(on, 200.0, 80.0) + np.random.default_rng(0).normal(0, 3, depth.shape)
    return depth, texture, np.stack([xs, ys], axis=-1)


def test_metric_sections_remove_the_crest_parallax():
    """Seen obliquely over sloping tissue, image-space sections pair the crest with tissue beside
    the point under it (error slope·height·tan(view)); in-plane coordinates pair it with its own."""
    for slope in (0.25, 0.0, -0.25):
        depth, tex, coords = _oblique_view(slope=slope)
        metric = feature_height(depth, tex, coords_mm=coords)
        image = feature_height(depth, tex)
        assert metric.height_mm == pytest.approx(0.72, abs=0.004), slope
        # image space: off by about −slope · 0.72 · tan 30° (0.10 mm), right only on level tissue
        assert image.height_mm - 0.72 == pytest.approx(
            -slope * 0.72 * np.tan(np.radians(30.0)), abs=0.03
        ), slope
