"""Geometry: exact projector column / phase on a plane, distortion, the ideal Eq. (5) oracle."""

from __future__ import annotations

import math

import cv2
import numpy as np

from app.devices.sim import default_rig
from app.devices.sim.ideal import eq5_height, ideal_calibration


def _sample_pixels(h: int, w: int, n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return rng.integers(0, h, n), rng.integers(0, w, n)


def test_plane_gives_exact_projector_column_and_phase(plane_world):
    r = plane_world.renderer
    rig = plane_world.rig
    hf = plane_world.scene.surface
    h, w = r.shape
    v, u = _sample_pixels(h, w)
    # Independent computation: back-project, intersect the plane analytically, project with cv2.
    K = rig.camera.K
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.size)], -1)
    n = hf.axes[:, 2]
    t = (n @ hf.origin) / (rays @ n)
    pts = rays * t[:, None]
    proj = rig.projector
    rvec, _ = cv2.Rodrigues(proj.R.T)
    tvec = -proj.R.T @ proj.centre
    uv, _ = cv2.projectPoints(pts, rvec, tvec, proj.K, np.zeros(5))
    xp_expected = uv[:, 0, 0]
    assert np.max(np.abs(r.xp[v, u] - xp_expected)) < 1e-6
    np.testing.assert_allclose(r.points[v, u], pts, atol=1e-9)
    # The phase the frames are rendered with: φ_k = 2π k x_p / w, stored as cos/sin.
    ck, sk = r._phase_tables()
    for fi, k in enumerate(r.schedule.frequencies):
        phi = 2 * math.pi * k * xp_expected / r.schedule.width
        idx = v * w + u
        assert np.max(np.abs(ck[fi, idx] - np.cos(phi))) < 1e-5
        assert np.max(np.abs(sk[fi, idx] - np.sin(phi))) < 1e-5


def test_distorted_rays_reproject_to_their_pixels():
    rig = default_rig(distortion=True)
    cam = rig.camera
    u = np.array([0.0, 100.5, 691.5, 1383.0, 20.0])
    v = np.array([0.0, 900.0, 515.5, 1031.0, 1000.0])
    rays = cam.rays(u, v)
    uv = cam.project(rays * 40.0)
    np.testing.assert_allclose(uv[:, 0], u, atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], v, atol=1e-6)


def test_reference_plane_matches_design():
    rig = default_rig()
    ref = rig.reference
    assert abs(np.linalg.norm(ref.normal) - 1) < 1e-12
    assert ref.normal[2] < -0.99  # faces the scope
    assert 40.0 < ref.offset_mm < 50.0  # camera centre height = distance of the far plane
    assert abs(ref.height(rig.reference_point_mm)) < 1e-9
    # The scopes converge inside the 25–50 mm working distance.
    d = rig.projector.R[:, 2]
    t = rig.projector.centre[0] / -d[0]
    assert 25.0 < (rig.projector.centre + t * d)[2] < 50.0


def test_ideal_calibration_reproduces_truth_from_true_phase(dof_world):
    r = dof_world.renderer
    cal = ideal_calibration(dof_world.rig, r.schedule)
    depth, points = r.truth()
    h, w = r.shape
    v, u = np.mgrid[0:h, 0:w]
    phi = 2 * math.pi * r.schedule.frequencies[-1] * r.xp / r.schedule.width
    ok = np.isfinite(depth)
    assert ok.mean() > 0.5 and np.nanmax(depth) - np.nanmin(depth) > 15.0
    z = eq5_height(cal, phi[ok], u[ok].astype(float), v[ok].astype(float))
    err = np.abs(z - depth[ok].astype(np.float64))
    assert err.max() < 1e-3  # truth stored as float32 (≈ 1e-6 mm); ≪ 0.01 mm
    assert np.all(cal.numerator[5:] == 0) and np.all(cal.denominator[6:] == 0)
