"""Coverage numerics on analytic board poses: the default twin rig's camera and projector, boards
placed exactly (no rendering), their corners projected and their phases from the projector model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.calib.coverage import (
    CoverageSpec,
    PoseGeometry,
    board_views,
    coverage_map,
    model_sigma,
    suggest_pose,
)
from app.core.board import BoardSpec
from app.devices.sim.optics import SimRig, default_rig, rotation_y
from app.devices.sim.scenes import board_points_mm, board_poses
from app.devices.sim.scenes.base import frame_from_normal

BOARD = BoardSpec("checkerboard", 12, 9, 1.4)
FRINGES, PROJ_W = 36, 608


def _views(
    rig: SimRig, poses: list[tuple[np.ndarray, np.ndarray]], phase_noise_rad: float = 0.0
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Per pose: detected corners (exact projections), board points, and the (H, W) finest phase
    of the board's plane (the projector column of each pixel's ray on it, plus seeded noise)."""
    rng = np.random.default_rng(5)
    obj = board_points_mm(BOARD)
    rays = rig.camera.pixel_rays()
    img, objs, phases = [], [], []
    for origin, axes in poses:
        pts = origin + obj @ axes.T
        img.append(rig.camera.project(pts).astype(np.float32))
        objs.append(obj.astype(np.float32))
        n = axes[:, 2]
        x = rays * ((n @ origin) / (rays @ n))[..., None]
        col = rig.projector.column(x)
        phi = 2 * np.pi * FRINGES * (col + 0.5) / PROJ_W
        phases.append((phi + rng.normal(0.0, phase_noise_rad, phi.shape)).astype(np.float32))
    return img, objs, phases


def _heights(rig: SimRig, pts: np.ndarray) -> np.ndarray:
    return pts @ rig.reference.normal + rig.reference.offset_mm


def test_board_views_recover_heights_and_tilt_signs() -> None:
    rig = default_rig(distortion=False)
    poses = board_poses(rig, 6, seed=1)
    # one extra pose with a known tilt: right edge toward the scope by 20°, 10 mm up
    ref = rig.reference
    normal = rotation_y(20.0) @ ref.normal
    normal = normal / np.linalg.norm(normal)
    origin = np.array([0.0, 0.0, (10.0 - ref.offset_mm) / ref.normal[2]])
    poses.append(frame_from_normal(origin, normal))
    img, obj, _ = _views(rig, poses)
    views = board_views(img, obj, rig.image_size)
    assert len(views.poses) == len(poses)
    # heights of every board point against the truth (grid of 13 x 13 over the corners)
    for (o, axes), g in zip(poses, views.poses, strict=True):
        s = np.linspace(-(BOARD.cols - 1) / 2, (BOARD.cols - 1) / 2, 13) * BOARD.pitch_mm
        t = np.linspace(-(BOARD.rows - 1) / 2, (BOARD.rows - 1) / 2, 13) * BOARD.pitch_mm
        ss, tt = np.meshgrid(s, t)
        truth = _heights(rig, o + np.stack([ss.ravel(), tt.ravel(), 0 * ss.ravel()], 1) @ axes.T)
        assert np.max(np.abs(g.height_mm - truth)) < 0.05
    assert (
        abs(views.poses[0].tilt_vertical_deg) < 0.5
        and abs(views.poses[0].tilt_horizontal_deg) < 0.5
    )
    # the known pose: its normal turned toward -x, so its right edge is nearer the scope
    last = views.poses[-1]
    assert last.tilt_vertical_deg == pytest.approx(20.0, abs=1.0)
    right = last.height_mm[last.uv[:, 0] > np.median(last.uv[:, 0])].mean()
    left = last.height_mm[last.uv[:, 0] < np.median(last.uv[:, 0])].mean()
    assert right > left + 2.0  # half the board width x tan 20°: 2.8 mm


def test_coverage_counts_cells_and_share() -> None:
    spec = CoverageSpec(cells=(3, 3), height_range_mm=(0.0, 20.0), height_bins=2, target_share=0.5)
    # two poses: one point each in known cells; one point outside the volume counts nowhere
    p0 = PoseGeometry(np.array([[10.0, 10.0], [150.0, 150.0]]), np.array([1.0, 25.0]), 0.0, 0.0)
    p1 = PoseGeometry(np.array([[290.0, 290.0], [150.0, 10.0]]), np.array([15.0, 9.99]), 20.0, 0.0)
    cov = coverage_map([p0, p1], (300, 300), spec=spec)
    assert cov.points.shape == (2, 3, 3)
    expected = np.zeros((2, 3, 3), int)
    expected[0, 0, 0] = expected[1, 2, 2] = expected[0, 0, 1] = 1
    assert np.array_equal(cov.points, expected)
    assert cov.covered_share == pytest.approx(3 / 18)
    assert np.isnan(cov.sigma_mm).all() and not cov.reached  # no model: σ undefined
    # a σ_model within the tolerance (the validity rule's, ~0.1 mm) everywhere below 10 mm
    # makes those cells calibrated; 1 mm above fails it
    assert 1e-4 < spec.sigma_tolerance_mm < 1.0
    cov2 = coverage_map(
        [p0, p1, p1], (300, 300), spec=spec, sigma=lambda uv, z: np.where(z < 10.0, 1e-4, 1.0)
    )
    assert cov2.calibrated[0].all() and cov2.calibrated_share == pytest.approx(10 / 18)
    assert cov2.reached
    assert cov2.to_dict()["sigma_model_um"][0][0][0] == pytest.approx(0.1)


def test_suggestion_names_the_emptiest_ninth_and_an_unused_tilt() -> None:
    spec = CoverageSpec(cells=(6, 6), height_bins=4)
    w, h = 600, 600
    # everything covered except the lower-left ninth at the 10-15 mm bin
    uu, vv = np.meshgrid(np.arange(25, 600, 50.0), np.arange(25, 600, 50.0))
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    poses = []
    for z in (2.5, 7.5, 12.5, 17.5):
        keep = ~((uv[:, 0] < 200) & (uv[:, 1] > 400)) if z == 12.5 else np.ones(len(uv), bool)
        poses.append(PoseGeometry(uv[keep], np.full(int(keep.sum()), z), 25.0, 25.0))
    cov = coverage_map(poses, (w, h), spec=spec)
    advice = suggest_pose(cov, poses)
    assert advice.region == "lower-left" and advice.height_mm == pytest.approx(12.5)
    assert (advice.u_px, advice.v_px) == (100.0, 500.0)
    # every pose so far tilted right/bottom edge toward the scope: the advice tilts otherwise
    assert (advice.tilt_vertical_deg, advice.tilt_horizontal_deg) != (25.0, 25.0)
    assert "lower-left" in advice.text and "about 12 mm" in advice.text
    assert "deg about the vertical axis" in advice.text
    assert suggest_pose(coverage_map([], (w, h), spec=spec), []).height_mm == 0.0


def test_model_sigma_from_the_jackknife_grows_away_from_the_boards() -> None:
    rig = default_rig(distortion=False)
    poses = board_poses(rig, 8, seed=0)
    img, obj, phases = _views(rig, poses, phase_noise_rad=0.02)
    views = board_views(img, obj, rig.image_size)
    assert (
        model_sigma(views, phases[:2], img[:2], fringes=FRINGES, projector_width_px=PROJ_W) is None
    )
    sigma = model_sigma(views, phases, img, fringes=FRINGES, projector_width_px=PROJ_W)
    assert sigma is not None
    spec = CoverageSpec()
    cov = coverage_map(views.poses, rig.image_size, sigma=sigma, spec=spec)
    s = cov.sigma_mm
    assert np.isfinite(s).all()
    # noisy phases: σ_model is small where the boards were and grows far beyond their heights
    inside = s[cov.covered]
    assert 1e-5 < np.median(inside) < 5e-3
    far = coverage_map(
        views.poses,
        rig.image_size,
        sigma=sigma,
        spec=CoverageSpec(height_range_mm=(40.0, 60.0), height_bins=1),
    ).sigma_mm
    print(
        f"\nsigma_model median {1000 * np.median(inside):.2f} um inside, "
        f"{1000 * np.median(far):.2f} um at 40-60 mm"
    )
    assert np.median(far) > 3 * np.median(inside)
    print(f"\n{cov.table()}")
    assert math.isfinite(cov.calibrated_share) and cov.calibrated_share >= cov.covered_share
