"""Measurements against analytic answers (planes, a sphere, a bump) and σ against Monte-Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.analysis import measure as M

H, W, F = 160, 200, 400.0
CX, CY = (W - 1) / 2, (H - 1) / 2
VV, UU = np.mgrid[0:H, 0:W].astype(np.float64)
RX, RY = (UU - CX) / F, (VV - CY) / F


def rays_to(t: np.ndarray) -> np.ndarray:
    return np.stack([RX * t, RY * t, t], -1)


def plane(normal=(0.0, 0.0, 1.0), d=50.0) -> np.ndarray:
    n = np.asarray(normal)
    return rays_to(d / (n[0] * RX + n[1] * RY + n[2]))


def sphere(zc=60.0, r=20.0) -> np.ndarray:
    """Front surface of a sphere centred on the optical axis (NaN off the sphere)."""
    rn = np.sqrt(RX**2 + RY**2 + 1)
    cos_a = 1 / rn
    disc = r**2 - zc**2 * (1 - cos_a**2)
    with np.errstate(invalid="ignore"):
        dist = zc * cos_a - np.sqrt(disc)
    return rays_to(np.where(disc > 0, dist / rn, np.nan))


def noisy(p: np.ndarray, sig: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Height noise along each point's ray (reference normal = optical axis): dX = X/Z · dh."""
    return p + p / p[..., 2:3] * rng.normal(0.0, 1.0, sig.shape)[..., None] * sig[..., None]


def ones(p):
    return np.all(np.isfinite(p), -1)


def test_length_on_a_fronto_parallel_plane():
    p = plane()
    m = M.length(p, ones(p), np.full((H, W), 0.01), [(20, 30), (180, 30)])
    assert m.value_mm == pytest.approx(160 / F * 50, rel=1e-9)
    # noise along z, segment lateral: only the rays' slant carries noise into the length
    assert 0 < m.sigma_mm < 0.01
    assert [p.pixel for p in m.points] == [(20, 30), (180, 30)] and not any(
        p.snapped for p in m.points
    )


def test_point_to_line_and_depth_analytic():
    p = plane()
    ok = ones(p)
    m = M.point_to_line(p, ok, None, [(100, 130), (10, 30), (190, 30)])
    assert m.value_mm == pytest.approx(100 / F * 50, rel=1e-9)
    assert math.isnan(m.sigma_mm)  # σ unknown
    # a point on the plane through three others on the same (tilted) plane: depth 0
    t = plane((0.4, -0.2, 1.0), 45.0)
    m = M.depth(t, ones(t), np.full((H, W), 0.02), [(77, 91), (10, 10), (190, 20), (100, 150)])
    assert abs(m.value_mm) < 1e-9
    # sphere pole against the plane of three rim points at one image radius: R(1 − cos θ), positive
    # (nearer)
    s = sphere()
    rho = 30.0
    ang = np.deg2rad([90, 210, 330])
    ref = [(CX + rho * math.cos(a), CY + rho * math.sin(a)) for a in ang]
    m = M.depth(s, ones(s), None, [(CX, CY), *ref], snap_px=0)
    zs = [s[int(round(v)), int(round(u)), 2] for u, v in ref]
    pole = s[int(round(CY)), int(round(CX)), 2]
    assert m.value_mm > 0
    assert m.value_mm == pytest.approx(np.mean(zs) - pole, abs=0.01)


def test_area_on_a_tilted_plane_is_the_surface_area():
    p = plane((0.5, 0.2, 1.0), 50.0)  # ~29° tilt: projected area is ~13 % smaller
    poly = [(30, 30), (170, 40), (140, 130), (50, 120), (80, 80)]  # concave
    m = M.area(p, ones(p), None, poly)
    v = np.array([p[b, a] for a, b in poly])
    true = 0.5 * np.linalg.norm(sum(np.cross(v[i], v[(i + 1) % len(v)]) for i in range(len(v))))
    assert m.value_mm == pytest.approx(true, rel=2e-4)


def test_area_of_a_sphere_cap():
    zc, r = 60.0, 20.0
    s = sphere(zc, r)
    rho = 50.0  # px; a 180-gon ≈ the circle
    ang = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    poly = [(CX + rho * math.cos(a), CY + rho * math.sin(a)) for a in ang]
    m = M.area(s, ones(s), None, poly, snap_px=0)
    alpha = math.atan(rho / F)
    t = zc * math.cos(alpha) - math.sqrt(r**2 - zc**2 * math.sin(alpha) ** 2)
    cos_theta = (zc - t * math.cos(alpha)) / r
    cap = 2 * math.pi * r**2 * (1 - cos_theta)
    flat = math.pi * (t * math.sin(alpha)) ** 2  # the projection's disc: the cap is clearly larger
    assert cap > 1.015 * flat
    # the 180-gon's chords (−0.02 %) and the sampling: < 0.1 % (a sixteenth of cap − projection)
    assert m.value_mm == pytest.approx(cap, rel=1e-3)


def bump_surface(height=1.0, width_mm=2.0, z0=50.0):
    t = np.full((H, W), z0)
    for _ in range(30):  # fixed point of z = z0 − bump(x, y)
        x, y = RX * t, RY * t
        t = z0 - height * np.exp(-(x**2 + y**2) / (2 * width_mm**2))
    return rays_to(t)


def test_profile_of_a_known_bump_against_its_chord_and_a_plane():
    b = bump_surface()
    ok = ones(b)
    m = M.profile(b, ok, np.full((H, W), 0.01), [(10, CY), (W - 11, CY)], snap_px=0)
    prof = m.profile
    assert prof is not None and len(prof.pixels) == W - 20
    assert np.all(np.diff(prof.pixels[:, 0]) == 1)
    assert m.value_mm == pytest.approx(1.0, abs=2e-3)  # the peak, toward the scope
    assert abs(prof.height_mm[0]) < 1e-9 and abs(prof.height_mm[-1]) < 1e-6
    # the same against a plane of three far points on the flat part
    m2 = M.profile(
        b, ok, None, [(10, CY), (W - 11, CY)], reference=[(5, 5), (W - 5, 5), (5, H - 5)]
    )
    assert m2.value_mm == pytest.approx(1.0, abs=2e-3)
    assert m2.extra["reference"] == "plane"
    assert m2.profile is not None and np.nanmax(m2.profile.distance_mm) > 0


@pytest.mark.parametrize("kind", ["length", "point_to_line", "depth", "profile", "area"])
def test_sigma_matches_monte_carlo(kind):
    rng = np.random.default_rng(7)
    base = sphere(60.0, 25.0) if kind in ("area", "profile") else plane((0.3, 0.1, 1.0), 40.0)
    ok = ones(base)
    sig = np.where(ok, 0.01 + 0.03 * (UU / W), 0.0)  # σ varies across the image
    pix = {
        "length": [(30, 40), (160, 120)],
        "point_to_line": [(100, 20), (30, 120), (170, 140)],
        "depth": [(100, 80), (30, 30), (170, 40), (90, 140)],
        "profile": [(40, 80), (160, 80)],
        "area": [(60, 50), (140, 55), (130, 110), (70, 105)],
    }[kind]
    m = M.measure(kind, base, ok, sig, pix)
    vals = []
    for _ in range(300):
        vals.append(
            M.measure(kind, noisy(base, sig, rng), ok, sig, pix).value_mm
            if kind != "profile"
            else M.measure(kind, noisy(base, sig, rng), ok, sig, pix).profile.height_mm[30]
        )
    ref = m.sigma_mm if kind != "profile" else m.profile.sigma_mm[30]
    observed = float(np.std(vals))
    assert observed / ref == pytest.approx(1.0, abs=0.15)  # 300 draws: std of a std ≈ 4 %
    if kind == "area":  # the roughness correction removes the noise's inflation of the area
        assert (
            abs(np.mean(vals) - m.extra["raw_mm2"])
            < 3 * observed / math.sqrt(300) + 1e-3 * m.value_mm
        )


def test_calibration_term_adds_in_quadrature():
    p = plane((0.3, 0.1, 1.0), 40.0)
    ok = ones(p)
    sig = np.full((H, W), 0.02)
    for kind, pix in (
        ("length", [(30, 40), (160, 120)]),
        ("depth", [(100, 80), (30, 30), (170, 40), (90, 140)]),
        ("profile", [(40, 80), (160, 80)]),
        ("area", [(60, 50), (140, 55), (130, 110), (70, 105)]),
    ):
        base = M.measure(kind, p, ok, sig, pix)
        m = M.measure(kind, p, ok, sig, pix, calibration_sigma_mm=0.01)
        assert m.value_mm == base.value_mm
        assert m.extra["sigma_noise_mm"] == pytest.approx(base.sigma_mm, rel=1e-9)
        assert m.sigma_mm == pytest.approx(
            math.hypot(base.sigma_mm, m.extra["sigma_calibration_mm"]), rel=1e-9
        )
        if kind != "area":  # the same propagation with σ 0.01 for every point: half the noise's
            assert m.extra["sigma_calibration_mm"] == pytest.approx(0.5 * base.sigma_mm, rel=1e-6)
        else:  # systematic: not reduced by the box means, so larger than the noise's half
            assert m.extra["sigma_calibration_mm"] > 0.5 * base.sigma_mm
    with pytest.raises(ValueError, match="calibration_sigma_mm"):
        M.length(p, ok, sig, [(1, 1), (5, 5)], calibration_sigma_mm=-1)


def test_snapping_and_refusals_name_the_point():
    p = plane()
    ok = ones(p)
    ok[50:55, 50:55] = False
    reason = np.where(ok, 0, 1).astype(np.uint8)
    m = M.length(p, ok, None, [(52, 50), (150, 100)], reason=reason)
    assert m.points[0].snapped and m.points[0].snap_px == 1.0 and m.points[0].pixel == (52, 49)
    with pytest.raises(
        ValueError,
        match=r"point 2 \(52, 52\): invalid pixel \(LOW_MODULATION\) and no valid pixel "
        r"within 2 px",
    ):
        M.length(p, ok, None, [(150, 100), (52, 52)], snap_px=2, reason=reason)
    with pytest.raises(ValueError, match=r"point 1 \(-3, 10\): outside the 200x160 image"):
        M.length(p, ok, None, [(-3, 10), (10, 10)])
    with pytest.raises(ValueError, match="length: needs exactly 2 points, got 1"):
        M.length(p, ok, None, [(10, 10)])
    with pytest.raises(ValueError, match="point 2 .*same pixel as point 1"):
        M.length(p, ok, None, [(10, 10), (10.2, 9.9)])
    with pytest.raises(ValueError, match="points 2 and 3 .* coincide"):
        M.point_to_line(p, ok, None, [(100, 100), (10, 10), (10, 10)])
    with pytest.raises(ValueError, match="points 2 .*, 3 .*, 4 .*: collinear"):
        M.depth(p, ok, None, [(100, 100), (10, 10), (20, 20), (30, 30)])
    # nearly collinear: ill-defined
    with pytest.raises(ValueError, match=r"smallest angle is 2\.\d° < 5°"):
        M.depth(p, ok, None, [(100, 100), (10, 10), (110, 10), (60, 12)])
    assert M.depth(
        p, ok, None, [(100, 100), (10, 10), (110, 10), (60, 20)]
    ).value_mm == pytest.approx(0, abs=1e-9)
    with pytest.raises(ValueError, match="area: needs at least 3 points, got 2"):
        M.area(p, ok, None, [(10, 10), (20, 20)])
    with pytest.raises(ValueError, match="edges 1-2 and 3-4 cross"):
        M.area(p, ok, None, [(10, 10), (100, 100), (100, 10), (10, 100)])
    with pytest.raises(ValueError, match=r"only 44 % of the polygon's pixels are valid; a "
                                         r"measurement needs at least 50 %"):
        big = ok.copy()
        big[60:120, 60:120] = False
        M.area(p, big, None, [(60, 60), (140, 60), (140, 140), (60, 140)])
    with pytest.raises(ValueError, match="a profile takes at most 20000 samples"):
        M.profile(p, ok, None, [(10, 10), (190, 150)] * 120)
    with pytest.raises(ValueError, match="kind: expected one of"):
        M.measure("volume", p, ok, None, [(1, 1)])
    with pytest.raises(ValueError, match="reference: only a profile"):
        M.measure("length", p, ok, None, [(1, 1), (5, 5)], reference=[(1, 1), (2, 2), (3, 1)])


def test_profile_gap_and_result_to_dict():
    p = plane()
    ok = ones(p)
    ok[80, 100:105] = False
    m = M.profile(p, ok, np.full((H, W), 0.02), [(50, 80), (150, 80)])
    assert m.profile is not None
    assert (
        np.isnan(m.profile.height_mm[50:55]).all() and np.isfinite(m.profile.height_mm[:50]).all()
    )
    d = m.to_dict()
    assert d["kind"] == "profile" and d["profile"]["height_mm"][50] is None and d["unit"] == "mm"
    assert len(d["points"]) == 2 and d["snapped"] is False


def test_calibration_term_correlated_by_distance():
    """Independent (length 0) → sqrt(Σ g²)·s; one shared height error (a huge length) → the
    change of the value when every point's height moves by s; in between, in between."""
    p = plane((0.3, 0.1, 1.0), 40.0)
    ok = ones(p)
    sig = np.full((H, W), 0.02)
    pix = [(30, 40), (160, 120)]
    s = 0.01
    indep = M.measure("length", p, ok, sig, pix, calibration_sigma_mm=s).extra[
        "sigma_calibration_mm"
    ]
    common = M.measure("length", p, ok, sig, pix, calibration_sigma_mm=s,
                       calibration_length_mm=1e9).extra["sigma_calibration_mm"]
    mid = M.measure("length", p, ok, sig, pix, calibration_sigma_mm=s,
                    calibration_length_mm=5.0).extra["sigma_calibration_mm"]
    x = np.array([p[v, u] for u, v in pix], np.float64)
    n = np.array([0.0, 0.0, 1.0])

    def moved(e):  # every point's height by e: along its ray by X / (n·X) per mm
        y = x + e * x / (x @ n)[:, None]
        return float(np.linalg.norm(y[1] - y[0]))

    assert common == pytest.approx(abs(moved(s) - moved(-s)) / 2, rel=1e-4)
    assert min(indep, common) < mid < max(indep, common)
    # an area: a shared error scales it, independent ones mostly cancel
    apix = [(60, 50), (140, 55), (130, 110), (70, 105)]
    a0 = M.measure("area", p, ok, sig, apix, calibration_sigma_mm=s).extra["sigma_calibration_mm"]
    a1 = M.measure("area", p, ok, sig, apix, calibration_sigma_mm=s,
                   calibration_length_mm=1e9).extra["sigma_calibration_mm"]
    assert a1 > 2 * a0 > 0
    with pytest.raises(ValueError, match="calibration_length_mm"):
        M.length(p, ok, sig, pix, calibration_sigma_mm=s, calibration_length_mm=-1.0)


@pytest.mark.parametrize("surface", ["sphere", "tilted"])
def test_area_measures_through_holes_within_its_sigma(surface: str):
    """Live maps have 9 x 9 holes (grown motion flags): an area keeps its value, says coverage."""
    p = sphere() if surface == "sphere" else plane((0.4, -0.2, 1.0), 45.0)
    ok, sig = ones(p), np.full((H, W), 0.02)
    poly = [(CX - 40, CY - 40), (CX + 40, CY - 40), (CX + 40, CY + 40), (CX - 40, CY + 40)]
    whole = M.area(p, ok, sig, poly)
    assert whole.extra["coverage"] == 1.0 and whole.extra["samples_filled"] == 0
    rng = np.random.default_rng(1)
    holes = ok.copy()
    for _ in range(40):  # anywhere: inside, across the edges, on the vertices
        y, x = rng.integers(0, H - 9), rng.integers(0, W - 9)
        holes[y:y + 9, x:x + 9] = False
        one = ok.copy()
        one[y:y + 9, x:x + 9] = False
        m = M.area(p, one, sig, poly)
        assert abs(m.value_mm - whole.value_mm) < 0.5 * m.sigma_mm
    m = M.area(p, holes, sig, poly)
    assert 0.8 < m.extra["coverage"] < 0.95 and m.extra["samples_filled"] > 20
    assert abs(m.value_mm - whole.value_mm) < 0.5 * m.sigma_mm
    assert 0.9 * whole.sigma_mm < m.sigma_mm < 1.2 * whole.sigma_mm
    assert all(not q.snapped for q in m.points)  # vertices stay where clicked, in holes too


def test_area_sigma_through_holes_matches_monte_carlo():
    rng = np.random.default_rng(11)
    base = sphere(60.0, 25.0)
    ok = ones(base)
    for y, x in ((45, 55), (70, 90), (100, 125), (52, 136), (95, 66)):  # on vertices, edges, inside
        ok[y:y + 9, x:x + 9] = False
    sig = np.where(ok, 0.01 + 0.03 * (UU / W), 0.0)
    pix = [(60, 50), (140, 55), (130, 110), (70, 105)]
    m = M.area(base, ok, sig, pix)
    assert m.extra["samples_filled"] >= 5 and m.extra["coverage"] < 0.97
    vals = [M.area(noisy(base, sig, rng), ok, sig, pix).value_mm for _ in range(300)]
    assert float(np.std(vals)) / m.sigma_mm == pytest.approx(1.0, abs=0.15)
    whole = M.area(base, ones(base), None, pix)
    assert abs(np.mean(vals) - whole.value_mm) < 3 * m.sigma_mm / math.sqrt(300) + 1e-3 * m.value_mm


def test_length_and_profile_ends_in_a_hole_are_filled_with_their_noise():
    rng = np.random.default_rng(5)
    p = plane((0.3, 0.1, 1.0), 40.0)
    ok = ones(p)
    ok[76:85, 146:155] = False  # a 9 x 9 hole around the second click: nothing within 3 px
    sig = np.where(ok, 0.02, 0.0)
    pix = [(30, 40), (150, 80)]
    with pytest.raises(ValueError,
                       match=r"point 2 \(150, 80\): invalid pixel and no valid pixel within 3 px"):
        M.length(p, ok, sig, pix)
    m = M.length(p, ok, sig, pix, fill_holes=True)
    truth = float(np.linalg.norm(p[80, 150] - p[40, 30]))
    assert m.points[1].filled and not m.points[0].filled and m.points[1].pixel == (150, 80)
    assert 0.5 < m.points[1].coverage < 1.0 and m.extra["coverage"] == m.points[1].coverage
    assert m.value_mm == pytest.approx(truth, abs=0.01 * m.sigma_mm)  # a plane: fitted near exact
    vals = [M.length(noisy(p, sig, rng), ok, sig, pix, fill_holes=True).value_mm
            for _ in range(300)]
    assert float(np.std(vals)) / m.sigma_mm == pytest.approx(1.0, abs=0.15)
    # the dispatcher passes it on; a profile's chord end in the hole is filled, its samples gaps
    assert M.measure("length", p, ok, sig, pix, fill_holes=True).value_mm == m.value_mm
    prof = M.measure("profile", p, ok, sig, [(100, 80), (150, 80)], fill_holes=True)
    assert prof.points[-1].filled and 0.5 < prof.extra["coverage"] < 1.0
    assert np.isnan(prof.profile.height_mm[-5:]).all()  # type: ignore[union-attr]
    # a hole whose surroundings are mostly invalid too is refused, saying so
    sparse = ok.copy()
    sparse[40:120, 110:190] &= rng.random((80, 80)) < 0.3
    sparse[76:85, 146:155] = False
    with pytest.raises(ValueError, match=r"point 2 \(150, 80\): invalid pixel in a hole whose "
                                         r"surroundings are \d+ % valid "
                                         r"\(a filled point needs 50 %\)"):
        M.length(p, sparse, sig, pix, fill_holes=True)


def test_profile_refused_below_half_coverage_with_the_figure():
    p = plane()
    ok = ones(p)
    ok[80, 60:130] = False  # 70 of the 101 samples
    with pytest.raises(ValueError, match=r"only 31 % of the profile's pixels are valid; a "
                                         r"measurement needs at least 50 %"):
        M.profile(p, ok, None, [(50, 80), (150, 80)])
    ok[80, 60:130] = True
    ok[80, 60:100] = False
    m = M.profile(p, ok, None, [(50, 80), (150, 80)])
    assert m.extra["coverage"] == pytest.approx(61 / 101, abs=1e-4)
