"""The joint (corners + phase) refinement is kept only while the corners stay within their noise.

A projector the model lacks (a decentred lens, an uncorrected gamma)
drags the joint fit's camera and poses toward its phase: the calibration must then keep the
corners-only camera, say why, and its corner reprojection must stay within 1.1 x OpenCV's
camera-only RMS on the same corners. A projector the model describes is still refined.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from app.calib import fit_observations, load_calibration
from app.calib.camera import DISTORTION_TERMS
from app.calib.fitting import PoseObservation
from app.calib.refine import corner_sum_squares
from app.capture.captureset import CaptureSet, write_capture_set
from app.cli import main
from tests.helpers.calib_fits import standard_noisy_observations
from tests.helpers.calib_rig import (
    BOARD,
    STANDARD_POSES,
    Rig,
    board_pose,
    fringe_stack,
    render_board,
    rot,
)

NOISE_PX = 0.05  # detected corners' noise per coordinate


@dataclass
class DefectProjectorRig(Rig):
    """The analytic rig whose projector lens has radial distortion k1 (which the depth model
    describes) and a decentring (OpenCV's tangential p1, p2, normalised coordinates), which no
    model here describes: the column of a point depends on its projector row the model cannot
    follow."""

    proj_k1: float = 0.08
    proj_p: tuple[float, float] = (0.01, 0.01)

    def phase_of_points(self, x: np.ndarray) -> np.ndarray:
        xp = (x - np.array(self.proj_center_mm)) @ rot(0, self.proj_yaw_deg).T
        xn, yn = xp[..., 0] / xp[..., 2], xp[..., 1] / xp[..., 2]
        r2 = xn * xn + yn * yn
        p1, p2 = self.proj_p
        xd = xn * (1.0 + self.proj_k1 * r2) + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        col = self.proj_f_px * xd + self.schedule.width / 2
        return 2 * math.pi * self.schedule.frequencies[-1] * col / self.schedule.width


def _observations(rig: Rig) -> list[PoseObservation]:
    rng = np.random.default_rng(7)
    return [rig.observe(BOARD, *board_pose(BOARD, *p[:4], p[4]), f"pose_{i:02d}", noise_px=NOISE_PX,
                        rng=rng) for i, p in enumerate(STANDARD_POSES)]


def _corner_rms(rep, obs) -> float:
    """RMS corner reprojection (px per corner) of the calibration's camera with the corner poses
    OpenCV finds for it — the camera the calibration keeps, judged on the same corners."""
    cal = rep.calibration
    obj = [o.object_points.astype(np.float64) for o in obs]
    img = [o.image_points.astype(np.float64).reshape(-1, 1, 2) for o in obs]
    rv, tv = [], []
    for o, i in zip(obj, img, strict=True):
        _, r, t = cv2.solvePnP(o, i, cal.camera_matrix, cal.dist_coeffs,
                               flags=cv2.SOLVEPNP_ITERATIVE)
        rv.append(r)
        tv.append(t)
    ssr, n = corner_sum_squares(obj, img, cal.camera_matrix, cal.dist_coeffs, rv, tv)
    return math.sqrt(ssr / n)


def test_defect_projector_refinement_rejected_corners_only_camera_kept():
    rig = DefectProjectorRig()
    obs = _observations(rig)
    size = (rig.width, rig.height)
    rep = fit_observations(obs, size, rig.schedule)
    corners_only = fit_observations(obs, size, rig.schedule, refine=False)
    ref = rep.refinement
    assert ref is not None and ref.accepted is False
    # what it would have cost
    assert ref.chi2 > ref.chi2_limit and ref.joint_rms_px > 1.1 * ref.corners_rms_px
    # the corners-only camera, exactly, and its reprojection within 1.1 x OpenCV's camera-only RMS
    kept, alone = rep.calibration, corners_only.calibration
    # (OpenCV's threaded solver may differ in the last bits between two runs)
    np.testing.assert_allclose(kept.camera_matrix, alone.camera_matrix, rtol=0, atol=1e-6)
    np.testing.assert_allclose(kept.dist_coeffs, alone.dist_coeffs, rtol=0, atol=1e-9)
    assert rep.camera is not None
    assert rep.reprojection_px <= 1.1 * rep.camera.rms_px
    assert _corner_rms(rep, obs) <= 1.1 * rep.camera.rms_px
    # the noise: the corners-only fit's residual, σ² = SSR₀ / (2n − p), ≈ the corners' 0.05 px
    assert ref.noise_px == pytest.approx(NOISE_PX, rel=0.15)
    assert ref.parameters == 4 + len(DISTORTION_TERMS[rep.camera.model]) + 6 * len(obs)
    assert "phase refinement rejected" in rep.table() and "corners-only camera" in rep.table()
    assert rep.calibration.extra["refinement"]["accepted"] is False


def test_a_radial_projector_lens_is_now_described_and_refined():
    """The same rig without the decentring: its radial lens bends each fringe along its length,
    which the projector model follows since the radial k1 (before, this rig's refinement was
    rejected); the projector's k1 comes back."""
    rig = DefectProjectorRig(proj_p=(0.0, 0.0))
    rep = fit_observations(_observations(rig), (rig.width, rig.height), rig.schedule)
    ref = rep.refinement
    assert ref is not None and ref.accepted is True, ref.reason
    assert rep.camera is not None and rep.reprojection_px <= 1.1 * rep.camera.rms_px
    assert rep.calibration.model.k1 == pytest.approx(rig.proj_k1, rel=0.05)


def test_projector_the_model_describes_is_still_refined(standard_noisy_fit):
    """The package's shared fit (tests/calib/conftest.py) of this module's observations of the
    analytic rig (the same poses, noise and seed)."""
    rig, rep = standard_noisy_fit
    for mine, shared in zip(_observations(rig), standard_noisy_observations(rig), strict=True):
        np.testing.assert_array_equal(mine.image_points, shared.image_points)
    ref = rep.refinement
    assert ref is not None and ref.accepted is True, ref.reason
    assert ref.chi2 <= ref.chi2_limit
    assert rep.camera is not None and rep.reprojection_px <= 1.1 * rep.camera.rms_px
    assert "phase refinement accepted" in rep.table()


def test_cli_prints_the_reason_and_writes_it(tmp_path, capsys):
    """``fringescope calibrate`` on rendered fringe sets of the defect rig, with a DMD gamma of 1.6
    left uncorrected (non-sinusoidal fringes): the reason is printed and recorded in the file."""
    rig = DefectProjectorRig()
    board = BOARD
    (tmp_path / "board.json").write_text(json.dumps(board.to_dict()))
    for i, (depth, ax, ay, az, sh) in enumerate(STANDARD_POSES):
        r, t = board_pose(board, depth, ax, ay, az, sh)
        albedo = render_board(board, r, t, rig).astype(np.float64) / 240.0
        phi = rig.plane_phase_map(r[:, 2], t).astype(np.float64)
        frames = fringe_stack(rig, phi, albedo, noise_dn=0.5, seed=i).astype(np.float64)
        gamma = (255.0 * (frames / 255.0) ** 1.6).round().clip(0, 255).astype(np.uint8)
        write_capture_set(tmp_path / f"pose_{i:02d}", CaptureSet(gamma, rig.schedule))
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(tmp_path), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "phase refinement rejected, the corners-only camera and poses are kept" in text
    saved = load_calibration(out).extra["refinement"]
    assert saved["accepted"] is False and saved["chi2"] > saved["chi2_limit"]
