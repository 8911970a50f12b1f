"""Undistorted rays and ray–plane intersection against known geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon.points import points_from_height, ray_tables


def test_rays_without_distortion_are_inverse_intrinsics():
    rig = Rig()
    rays = ray_tables(rig.K, np.zeros(5), (rig.width, rig.height), rig.n)
    truth = rig.rays()
    assert np.max(np.abs(rays.rx - truth[..., 0])) < 1e-12
    assert np.max(np.abs(rays.ry - truth[..., 1])) < 1e-12
    assert np.max(np.abs(rays.inv_m - 1.0 / (truth @ rig.n))) < 1e-12


def test_points_match_rig_surface_and_lie_on_their_height_plane():
    rig = Rig()
    h = bump_surface(rig)
    rays = ray_tables(rig.K, [], (rig.width, rig.height), rig.n)
    pts = points_from_height(h, rays, rig.plane_offset_mm)
    assert np.max(np.abs(pts - rig.points(h))) < 1e-9
    assert np.max(np.abs(pts @ rig.n + rig.plane_offset_mm - h)) < 1e-9
    nan_h = h.copy()
    nan_h[3, 4] = np.nan
    assert np.isnan(points_from_height(nan_h, rays, rig.plane_offset_mm)[3, 4]).all()


def test_distorted_rays_reproject_to_their_pixels():
    k = np.array([[300.0, 0, 70.2], [0, 310.0, 49.7], [0, 0, 1]])
    dist = np.array([-0.25, 0.08, 0.001, -0.0015, 0.0])
    w, h = 140, 100
    n = np.array([0.0, 0.0, -1.0])
    rays = ray_tables(k, dist, (w, h), n)
    xyz = np.stack([rays.rx, rays.ry, np.ones_like(rays.rx)], -1).reshape(-1, 3) * 50.0
    proj, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), k, dist)
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    assert np.max(np.abs(proj.reshape(h, w, 2) - np.stack([uu, vv], -1))) < 1e-6  # px


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((np.eye(2), [], (4, 3), [0, 0, 1.0]), "camera_matrix"),
        ((np.eye(3), [np.nan] * 5, (4, 3), [0, 0, 1.0]), "dist_coeffs"),
        ((np.eye(3), [], (0, 3), [0, 0, 1.0]), "image_size"),
        ((np.eye(3), [], (4, 3), [0, 1.0]), "plane_normal"),
    ],
)
def test_bad_input(args, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        ray_tables(*args)
