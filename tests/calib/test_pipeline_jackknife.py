"""The whole calibration refitted with each board pose left out (camera and its lens model,
reference plane, projector): its spread is σ_model, saved with the file and honest about the
reference plane and the lens model's extrapolation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.calib import fit_observations
from app.calib.camera import DISTORTION_TERMS, MODEL_LADDER
from app.calib.model import undistort_points
from app.core.calibration import Calibration
from app.core.geometric import GeometricModel, undistort_newton
from app.recon.model_sigma import model_sigma_table
from app.recon.points import calibration_ray_tables
from tests.helpers.calib_rig import BOARD, STANDARD_POSES, Rig, board_pose


def _calibration(noise_px: float, seed: int = 7) -> tuple[Calibration, Rig, list]:
    rig = Rig()
    rng = np.random.default_rng(seed)
    obs, truth = [], []
    for i, (d, ax, ay, az, sh) in enumerate(STANDARD_POSES):
        r, t = board_pose(BOARD, d, ax, ay, az, sh)
        truth.append((r, t))
        obs.append(rig.observe(BOARD, r, t, f"pose_{i:02d}", noise_px=noise_px, rng=rng))
    cal = fit_observations(obs, (rig.width, rig.height), rig.schedule, model="geometric",
                           refine=False).calibration
    return cal, rig, truth


def test_newton_undistortion_matches_opencv_on_strong_distortion():
    k = np.array([[900.0, 0.0, 330.0], [0.0, 905.0, 250.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.28, 0.09, 0.001, -0.0015, -0.01])
    rng = np.random.default_rng(0)
    uv = np.column_stack([rng.uniform(0, 660, 500), rng.uniform(0, 500, 500)])
    ref = undistort_points(uv, k, dist)
    # the start: another camera's rays of the same pixels (here the pinhole's)
    start = np.column_stack([(uv[:, 0] - 330.0) / 900.0, (uv[:, 1] - 250.0) / 905.0])
    got = undistort_newton(uv, k, dist, start)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    proj, _ = cv2.projectPoints(np.column_stack([got, np.ones(len(got))]), np.zeros(3),
                                np.zeros(3), k, dist)
    np.testing.assert_allclose(proj.reshape(-1, 2), uv, atol=1e-6)


@pytest.fixture(scope="module")
def solves_and_calibration() -> tuple[list[tuple[int, int, float]], Calibration, Rig, list]:
    """:func:`_calibration` with corner noise 0.1 px (seed 7), made once for the module's tests
    that read it (a geometric fit with its jackknife costs ~7 s of CPU); read only. First the
    projector solves it made with k1 and t_y free: (status, evaluations, t_y mm) each."""
    import scipy.optimize

    solves: list[tuple[int, int, float]] = []
    least_squares = scipy.optimize.least_squares

    def counted(fun, x0, *args, **kwargs):  # type: ignore[no-untyped-def]
        r = least_squares(fun, x0, *args, **kwargs)
        if len(x0) == 9:  # the geometric model's projector: rotation, t_x, t_z, f, c, k1, t_y
            solves.append((int(r.status), int(r.nfev), float(r.x[8])))
        return r

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scipy.optimize, "least_squares", counted)
        cal, rig, truth = _calibration(noise_px=0.1)
    return solves, cal, rig, truth


@pytest.fixture(scope="module")
def calibration_at_0p1_px(solves_and_calibration) -> tuple[Calibration, Rig, list]:
    return solves_and_calibration[1:]


def test_the_projector_offset_stays_physical_where_k1_is_noise(solves_and_calibration):
    """This rig's projector is a pinhole, so k1 is noise in the jackknife's k1 fits; t_y shows
    only through k1's bending, and as k1 → 0 with k1·t_y² held it became a 1/z² term of its
    own, fitting the camera's and plane's errors: 4 of 50 fits ran to t_y of 33-157 m and 5000
    evaluations (62 s of CPU). Under t_y's prior (σ a quarter of the ~90 mm working distance)
    each converges in under 100 evaluations and |t_y| stays under 213 mm (median 101): the prior
    is weak against thousands of points, but it bounds the run-off."""
    solves = solves_and_calibration[0]
    assert len(solves) >= 10
    assert all(status > 0 and nfev < 1000 and abs(ty) < 500.0 for status, nfev, ty in solves), \
        solves


def test_every_pose_left_out_refits_camera_plane_and_projector(calibration_at_0p1_px):
    cal, rig, _ = calibration_at_0p1_px
    model = cal.model
    assert isinstance(model, GeometricModel)
    assert len(model.pipeline) == len(STANDARD_POSES)
    # each refit's camera and plane differ from the others' (corner noise), none is the truth
    focal = np.array([p.camera_matrix[0, 0] for p in model.pipeline])
    offsets = np.array([p.plane.offset_mm for p in model.pipeline])
    assert np.ptp(focal) > 0 and np.ptp(offsets) > 0
    assert np.all(np.abs(focal / rig.f_px - 1.0) < 0.01)
    # the whole calibration's σ is at least the projector's alone (same poses; camera and plane
    # add to it) over the boards' region, and it is what the kernel's table holds
    u = np.array([320.0, 300.0, 350.0])
    v = np.array([240.0, 220.0, 260.0])
    rxy = undistort_points(np.column_stack([u, v]), cal.camera_matrix, cal.dist_coeffs)
    plane = cal.reference_plane
    for h in (0.0, 10.0, 20.0):
        total = model.height_sigma(u, v, rxy, np.full(3, h), plane)
        d = model.height_deviations(u, v, rxy, np.full(3, h), plane)
        projector = np.sqrt(np.sum(d**2, axis=0))
        assert np.all(total >= 0.5 * projector) and np.all(np.isfinite(total))
    rays = calibration_ray_tables(cal)
    table = model_sigma_table(cal, rays, (-2.0, 22.0))
    assert table is not None
    depth = np.full((rig.height, rig.width), 10.0, np.float32)
    sig = table.sigma_mm(depth)
    total = model.height_sigma(u, v, rxy, np.full(3, 10.0), plane)
    np.testing.assert_allclose(sig[v.astype(int), u.astype(int)], total, rtol=0.2, atol=2e-4)


def test_the_jackknife_sigma_covers_the_reference_plane_and_camera_errors():
    """Over noise draws the heights' error (against the true plane) at points across the field
    is within a few σ_model of the whole calibration; the projector-only jackknife misses it."""
    z_total, z_projector = [], []
    for seed in range(4):
        cal, rig, truth = _calibration(noise_px=0.15, seed=seed)
        model = cal.model
        assert isinstance(model, GeometricModel)
        rng = np.random.default_rng(seed)
        u = rng.uniform(60, 580, 200)
        v = rng.uniform(40, 440, 200)
        hz = rng.uniform(0.0, 20.0, 200)
        r0, t0 = truth[0]
        n = r0[:, 2] if r0[:, 2] @ t0 < 0 else -r0[:, 2]
        ray = rig.rays(u, v)
        x = ray * ((hz + n @ t0) / (ray @ n))[:, None]
        phi = rig.phase_of_points(x)
        rxy = undistort_points(np.column_stack([u, v]), cal.camera_matrix, cal.dist_coeffs)
        plane = cal.reference_plane
        err = model.height_at(u, v, rxy, phi, plane) - hz
        total = model.height_sigma(u, v, rxy, hz, plane)
        proj = np.sqrt(np.sum(model.height_deviations(u, v, rxy, hz, plane) ** 2, axis=0))
        z_total.append(err / total)
        z_projector.append(err / proj)
    zt, zp = np.concatenate(z_total), np.concatenate(z_projector)
    assert float(np.sqrt(np.mean(zt**2))) < 2.0
    assert float(np.sqrt(np.mean(zp**2))) > float(np.sqrt(np.mean(zt**2)))


def test_the_refits_are_saved_with_the_calibration_file(calibration_at_0p1_px):
    cal, _, _ = calibration_at_0p1_px
    again = Calibration.from_dict(cal.to_dict())
    assert isinstance(again.model, GeometricModel) and isinstance(cal.model, GeometricModel)
    assert len(again.model.pipeline) == len(cal.model.pipeline)
    assert cal.model.lens_alternative is not None and again.model.lens_alternative is not None
    np.testing.assert_array_equal(again.model.lens_alternative.dist_coeffs,
                                  cal.model.lens_alternative.dist_coeffs)
    u, v = np.array([100.0, 320.0]), np.array([80.0, 240.0])
    rxy = undistort_points(np.column_stack([u, v]), cal.camera_matrix, cal.dist_coeffs)
    h = np.array([5.0, 15.0])
    np.testing.assert_allclose(again.model.height_sigma(u, v, rxy, h, again.reference_plane),
                               cal.model.height_sigma(u, v, rxy, h, cal.reference_plane),
                               rtol=1e-9)
    data = cal.to_dict()
    data["model"]["pipeline_jackknife"][0]["camera_matrix"] = [[1.0, 0.0], [0.0, 1.0]]
    with pytest.raises(ValueError, match="pipeline_jackknife"):
        Calibration.from_dict(data)


def test_the_next_lens_model_is_refitted_and_its_row_added(calibration_at_0p1_px):
    """Beside the chosen lens model, the whole calibration refitted with the next one of the
    held-out ladder: its terms free, the others 0; σ_model² grows by the square of its height's
    difference from the model's at every place."""
    cal, _, _ = calibration_at_0p1_px
    model = cal.model
    assert isinstance(model, GeometricModel)
    ladder = MODEL_LADDER
    chosen = str(cal.extra["camera_model"]["distortion_model"])
    alt = model.lens_alternative
    assert chosen in ladder[:-1] and alt is not None
    other = ladder[ladder.index(chosen) + 1]
    free = set(DISTORTION_TERMS[other])
    assert all(alt.dist_coeffs[i] == 0.0 for i in range(5) if i not in free)
    assert any(alt.dist_coeffs[i] != 0.0 for i in free - set(DISTORTION_TERMS[chosen]))
    u = np.array([20.0, 320.0, 630.0])
    v = np.array([15.0, 240.0, 470.0])
    rxy = undistort_points(np.column_stack([u, v]), cal.camera_matrix, cal.dist_coeffs)
    h = np.array([0.0, 10.0, 20.0])
    plane = cal.reference_plane
    with_row = model.height_sigma(u, v, rxy, h, plane)
    phi = model.phase_at(u, v, rxy, h, plane)
    diff = alt.height_at(np.column_stack([u, v]), rxy, phi) - h
    model.lens_alternative = None
    try:
        without = model.height_sigma(u, v, rxy, h, plane)
    finally:
        model.lens_alternative = alt
    # the row counts beyond the field the held-out corners verified the chosen model to
    assert model.lens_verified_px is not None
    cx, cy, rx, ry = model.lens_verified_px
    beyond = ((u - cx) / rx) ** 2 + ((v - cy) / ry) ** 2 > 1.0
    assert beyond.any() and not beyond.all()
    np.testing.assert_allclose(with_row**2 - without**2, np.where(beyond, diff**2, 0.0),
                               rtol=1e-6, atol=1e-12)
    assert np.all(np.abs(diff) > 0)


def test_a_lengths_calibration_sigma_is_the_refits_own_spread_of_that_length(
        calibration_at_0p1_px):
    """Each refit puts the two pixels' phases on its own camera's rays at its own heights; the
    delete-one spread of the length between them (with the two alternatives' differences) is
    the length's calibration σ that ``Calibration.point_deviations`` gives, sideways moves
    included; moving the points along this calibration's rays alone gives a different σ. (Two
    pixels inside the ellipse the corners verified: the lens alternative's row is zero there;
    beyond it that row reaches a millimetre at this rig's corners, where first order and the
    refits' exact lengths part by a few per cent.)"""
    cal, _, _ = calibration_at_0p1_px
    model = cal.model
    assert isinstance(model, GeometricModel) and model.alternative is not None
    plane = cal.reference_plane
    uv = np.array([[200.0, 150.0], [450.0, 330.0]])
    rxy = undistort_points(uv, cal.camera_matrix, cal.dist_coeffs)
    h = np.array([2.0, 18.0])
    r3 = np.column_stack([rxy, np.ones(2)])
    pts = r3 * ((h - plane.offset_mm) / (r3 @ plane.normal))[:, None]
    phi = model.phase_at(uv[:, 0], uv[:, 1], rxy, h, plane)

    def length_of(camera_rays: np.ndarray, heights: np.ndarray, p: object) -> float:
        r = np.column_stack([camera_rays, np.ones(2)])
        x = r * ((heights - p.offset_mm) / (r @ p.normal))[:, None]  # type: ignore[attr-defined]
        return float(np.linalg.norm(x[1] - x[0]))

    refit = np.array([length_of(f.rays(uv, rxy), f.height_at(uv, rxy, phi), f.plane)
                      for f in model.pipeline])
    g = len(refit)
    var = (g - 1) / g * float(np.sum((refit - refit.mean()) ** 2))
    here = float(np.linalg.norm(pts[1] - pts[0]))
    alt_h = model.alternative.height_at(uv[:, 0], uv[:, 1], rxy, phi, plane)
    var += (length_of(rxy, alt_h, plane) - here) ** 2
    assert model.lens_verified_px is not None
    cx, cy, rx, ry = model.lens_verified_px
    assert all(((uv[:, 0] - cx) / rx) ** 2 + ((uv[:, 1] - cy) / ry) ** 2 < 1.0)
    grad = (pts[1] - pts[0]) / here
    rows = cal.point_deviations(pts)
    sigma = float(np.linalg.norm(rows[:, 1] @ grad - rows[:, 0] @ grad))
    assert sigma == pytest.approx(np.sqrt(var), rel=0.02)
    along = cal.height_deviations(pts)[:, :, None] * (r3 / (r3 @ plane.normal)[:, None])[None]
    sigma_along = float(np.linalg.norm(along[:, 1] @ grad - along[:, 0] @ grad))
    assert abs(sigma_along - sigma) > 0.05 * sigma
