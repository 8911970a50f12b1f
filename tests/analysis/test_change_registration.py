"""Rigid registration and the change along the normal, on a synthetic organised cloud."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from app.analysis.change import compare, project_to_pixels, register_rigid, surface_normals

H, W = 240, 320
K = np.array([[300.0, 0, (W - 1) / 2], [0, 300.0, (H - 1) / 2], [0, 0, 1]])
DIST = np.zeros(5)
SIGMA_MM = 0.02


def _surface(x: np.ndarray, y: np.ndarray, bump_mm: float = 0.0) -> np.ndarray:
    """Depth z (mm) of a wavy tissue-like surface at lateral (x, y) mm, optionally with a bump
    ``bump_mm`` high toward the camera, 3 mm across."""
    z = 40 + 2.0 * np.sin(x / 3.0) * np.cos(y / 4.0) + 0.05 * x + 1.5 * np.exp(
        -((x - 4) ** 2 + (y + 2) ** 2) / 20)
    r = np.hypot(x + 3, y - 2) / 1.5
    return z - np.where(r < 1, 0.5 * bump_mm * (1 + np.cos(math.pi * np.minimum(r, 1))), 0.0)


def _view(transform: np.ndarray, bump_mm: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) points and σ of the surface seen by a camera whose frame is moved by
    ``transform`` (scene → camera), with noise along the ray."""
    rng = np.random.default_rng(seed)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)
    inv = np.linalg.inv(transform)
    t = np.full((H, W), 40.0)
    for _ in range(200):  # fixed point: where the ray meets the surface (in the scene frame)
        p = rays * t[..., None]
        q = p @ inv[:3, :3].T + inv[:3, 3]
        zs = _surface(q[..., 0], q[..., 1], bump_mm)
        # move along the ray by the depth mismatch measured along the scene's z
        t += (zs - q[..., 2]) / (rays @ inv[:3, :3].T)[..., 2]
    t += SIGMA_MM * rng.standard_normal(t.shape)
    pts = (rays * t[..., None]).astype(np.float32)
    return pts, np.full((H, W), SIGMA_MM, np.float32)


def _moved(deg: float, shift: tuple[float, float, float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(np.radians(deg) * np.array([0.3, 1.0, 0.2])
                              / np.linalg.norm([0.3, 1.0, 0.2]))[0]
    c = np.array([0, 0, 40.0])  # about the scene's centre
    m[:3, 3] = c - m[:3, :3] @ c + np.asarray(shift)
    return m


@pytest.fixture(scope="module")
def reference():
    return _view(np.eye(4), 0.0, 1)


def test_registration_recovers_a_scope_motion_of_1mm_and_2deg(reference):
    ref_pts, ref_sig = reference
    motion = _moved(2.0, (0.6, -0.5, 0.6))
    pts, sig = _view(motion, 0.0, 2)
    icp = register_rigid(pts, ref_pts)
    assert icp.ok and icp.note == "" and icp.overlap > 0.8
    assert icp.rotation_deg == pytest.approx(2.0, abs=0.5)
    res = compare(pts[..., 2].copy(), sig, pts, ref_pts[..., 2].copy(), ref_sig, ref_pts,
                  camera_matrix=K, dist_coeffs=DIST)
    assert res.mode == "registered" and res.registration is not None
    reg = res.registration
    # the transform takes current camera coordinates to the reference camera's: motion⁻¹
    err = reg.transform @ motion
    assert math.degrees(math.acos(min(1, (np.trace(err[:3, :3]) - 1) / 2))) < 0.02
    assert np.linalg.norm(err[:3, 3]) < 0.02
    assert reg.rotation_deg == pytest.approx(2.0, abs=0.02)
    assert reg.residual_mm < 1.2 * math.sqrt(2) * SIGMA_MM
    assert res.cmap.changed_share < 1e-3


def test_the_registered_change_finds_a_bump_and_nothing_else(reference):
    ref_pts, ref_sig = reference
    pts, sig = _view(_moved(2.0, (0.6, -0.5, 0.6)), 0.3, 3)
    ref_depth = ref_pts[..., 2].copy()
    res = compare(pts[..., 2].copy(), sig, pts, ref_depth, ref_sig, ref_pts,
                  camera_matrix=K, dist_coeffs=DIST)
    assert res.mode == "registered" and res.registration is not None and res.registration.ok
    assert res.fixed_changed_share > 0.5  # pixel by pixel, everything "moved"
    cm = res.cmap
    # truth in the reference view: a 0.3 mm bump toward the scope (a rise)
    x, y = ref_pts[..., 0], ref_pts[..., 1]
    bump = np.hypot(x + 3, y - 2) < 0.75  # where it rises more than half its height
    assert bump.sum() > 50 and cm.changed[bump].mean() >= 0.9
    assert np.nanmedian(cm.delta[bump]) > 0.15
    far = np.hypot(x + 3, y - 2) > 3
    assert cm.changed[far].mean() < 1e-3
    assert np.nanstd(cm.delta[far]) < 1.5 * math.sqrt(2) * SIGMA_MM


def test_a_still_scope_is_compared_pixel_by_pixel(reference):
    ref_pts, ref_sig = reference
    pts, sig = _view(np.eye(4), 0.0, 4)
    res = compare(pts[..., 2].copy(), sig, pts, ref_pts[..., 2].copy(), ref_sig, ref_pts,
                  camera_matrix=K, dist_coeffs=DIST)
    assert res.mode == "fixed" and res.registration is None
    assert res.cmap.changed_share < 1e-3


def test_a_registration_that_cannot_match_says_so_and_shows_no_change(reference):
    ref_pts, ref_sig = reference
    far = ref_pts.copy()
    far[..., 2] += 30.0  # nothing within reach of the correspondence search
    res = compare(far[..., 2].copy(), ref_sig, far, ref_pts[..., 2].copy(), ref_sig, ref_pts,
                  camera_matrix=K, dist_coeffs=DIST)
    assert res.mode == "failed" and res.registration is not None
    assert not res.registration.ok and res.registration.note
    assert not res.cmap.changed.any() and res.cmap.compared == 0
    few = np.full_like(ref_pts, np.nan)
    reg = register_rigid(few, ref_pts)
    assert not reg.ok and "too few" in reg.note


def test_normals_point_to_the_camera(reference):
    ref_pts, _ = reference
    n = surface_normals(ref_pts)
    ok = np.isfinite(n).all(axis=2)
    assert ok.mean() > 0.9
    assert (np.einsum("ij,ij->i", n[ok], ref_pts[ok]) < 0).all()
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=1), 1, atol=1e-5)
    with pytest.raises(ValueError, match="step_px"):
        surface_normals(ref_pts, 0)



def test_a_collapsed_cloud_is_not_registered_and_is_no_crash():
    """Both clouds collapsed to the camera's centre (every point (0, 0, 0)): a handful of
    voxels, no point in front of the camera. The registration says so (failed) instead of
    passing a degenerate ICP on to a projection of no points."""
    h, w = 48, 64
    k = np.array([[200.0, 0, 32], [0, 200.0, 24], [0, 0, 1]])
    zero = np.zeros((h, w, 3), np.float32)
    sig = np.full((h, w), 0.05, np.float32)
    res = compare(np.ones((h, w), np.float32), sig, zero, np.zeros((h, w), np.float32), sig,
                  zero, camera_matrix=k, dist_coeffs=DIST)
    assert res.mode == "failed" and res.registration is not None
    assert "too few" in res.registration.note
    assert not res.cmap.changed.any()


def _calibration_error(amplitude_mm: float) -> np.ndarray:
    """(H, W) a smooth depth error that depends on the pixel (one calibration's): the same in
    every map, so a still scope's Δ cancels it and a moved one's does not."""
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    e = np.sin(uu / 9.0 + 0.4) * np.cos(vv / 11.0) + 0.5 * np.sin((uu + vv) / 7.0)
    return (amplitude_mm * e / e.std()).astype(np.float32)


def test_a_calibration_error_stated_as_sigma_model_is_no_change_after_a_scope_motion():
    """Both maps carry the same pixel-bound calibration error (1-σ 0.04 mm, twice the noise).
    Registered, its difference reads as change unless each map's σ_model states it: then it
    is an error shared by neighbours and nothing is flagged."""
    err = _calibration_error(0.04)

    def view(transform: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        pts, sig = _view(transform, 0.0, seed)
        # the error along each pixel's ray (z grows by err): where this pixel looks
        return (pts * (1 + err / pts[..., 2])[..., None]).astype(np.float32), sig

    ref_pts, ref_sig = view(np.eye(4), 11)
    pts, sig = view(_moved(2.0, (0.6, -0.5, 0.6)), 12)
    sm = np.full((H, W), 0.04, np.float32)
    args = (pts[..., 2].copy(), sig, pts, ref_pts[..., 2].copy(), ref_sig, ref_pts)
    plain = compare(*args, camera_matrix=K, dist_coeffs=DIST)
    stated = compare(*args, camera_matrix=K, dist_coeffs=DIST, sigma_model=sm,
                     ref_sigma_model=sm)
    print(f"\ncalibration error 0.04 mm: registered changed {100 * plain.cmap.changed_share:.3f}%"
          f" without sigma_model, {100 * stated.cmap.changed_share:.4f}% with it")
    assert plain.mode == stated.mode == "registered"
    assert plain.cmap.changed_share > 1e-3  # what it does unstated
    assert stated.cmap.changed_share <= 1e-4
    ok = np.isfinite(stated.cmap.sigma)
    assert (stated.cmap.sigma[ok] >= np.hypot(plain.cmap.sigma[ok], 0.04 * math.sqrt(2)) - 1e-6
            ).all()
    still = compare(*args[:2], ref_pts, *args[3:], camera_matrix=K, dist_coeffs=DIST,
                    register="never")  # a fixed scope: the same error cancels, nothing to add
    assert still.mode == "fixed"


def test_a_transform_that_puts_every_point_behind_the_camera_compares_nothing(reference):
    """No moved point projects into the image: an empty change map, not an error from the
    projection of no points."""
    from app.analysis.change import change_along_normal

    ref_pts, ref_sig = reference
    behind = np.eye(4)
    behind[2, 3] = -1000.0  # 1 m back: every point at z < 0
    cm = change_along_normal(ref_pts, ref_sig, ref_pts, ref_sig, behind, K, DIST)
    assert cm.compared == 0 and not cm.changed.any() and np.isnan(cm.delta).all()


@pytest.mark.parametrize("dist", [
    np.zeros(0), np.zeros(5),
    np.array([-0.05, 0.0, 0.0, 0.0, 0.0]),  # the twin's lens
    np.array([0.21, -0.33, 1.2e-3, -8e-4]),
    np.array([-0.12, 0.08, 1e-3, -1e-3, 0.015]),
    np.array([-0.12, 0.08, 1e-3, -1e-3, 0.015, 0.02, -0.01, 0.005]),  # rational
    np.array([-0.12, 0.08, 1e-3, -1e-3, 0.015, 0.02, -0.01, 0.005, 1e-3, -2e-4, 5e-4, 3e-4]),
    np.array([-0.12, 0.08, 1e-3, -1e-3, 0.015, 0, 0, 0, 0, 0, 0, 0, 0.01, -0.02]),  # tilted
])
def test_the_projection_is_opencvs_to_the_last_bit(dist: np.ndarray) -> None:
    """The registered comparison projects a whole map without OpenCV's Jacobian: the pixel
    coordinates must be OpenCV's exactly (a rounding apart would move a pixel's pairing)."""
    rng = np.random.default_rng(7)
    n = 200_000
    pts = np.column_stack([rng.uniform(-25, 25, n), rng.uniform(-20, 20, n),
                           rng.uniform(20, 90, n)])
    cam = np.array([[1650.3, 0.0, 691.5], [0.0, 1649.1, 515.5], [0.0, 0.0, 1.0]])
    expected, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam, dist)
    got = project_to_pixels(pts, cam, dist)
    assert got.shape == (n, 2) and got.dtype == np.float64
    assert np.array_equal(got, expected.reshape(-1, 2))
