"""The calibration fit against an analytic pinhole camera + projector rig (exact Eq. 5)."""

from __future__ import annotations

import numpy as np
import pytest

from app.calib import BoardSpec, fit_observations, height_mm, sample_phase
from app.core.calibration import Calibration
from app.core.eq5 import basis, evaluate, fit_eq5
from tests.helpers.calib_fits import standard_noisy_observations
from tests.helpers.calib_rig import BOARD, STANDARD_POSES, Rig, board_pose


def _observations(rig: Rig, poses=STANDARD_POSES, noise_px: float = 0.0):
    obs, truth = [], []
    rng = np.random.default_rng(7)
    for i, (d, ax, ay, az, sh) in enumerate(poses):
        r, t = board_pose(BOARD, d, ax, ay, az, sh)
        truth.append((r, t))
        obs.append(rig.observe(BOARD, r, t, f"pose_{i:02d}", noise_px=noise_px, rng=rng))
    return obs, truth


def _height_error(
    rig: Rig, cal: Calibration, ref: tuple[np.ndarray, np.ndarray], z_lo: float, z_hi: float
):
    """Max |model − truth| over random pixels of the board region and heights in [z_lo, z_hi]."""
    rng = np.random.default_rng(3)
    u = rng.uniform(200, 440, 4000)
    v = rng.uniform(150, 330, 4000)
    r0, t0 = ref
    n = r0[:, 2] if r0[:, 2] @ t0 < 0 else -r0[:, 2]
    hz = rng.uniform(z_lo, z_hi, u.size)
    ray = rig.rays(u, v)
    x = ray * ((hz + n @ t0) / (ray @ n))[:, None]
    return np.abs(height_mm(cal, u, v, rig.phase_of_points(x)) - hz)


@pytest.mark.parametrize("dense", [True, False])
def test_fit_reproduces_exact_rig(dense):
    rig = Rig()
    obs, truth = _observations(rig)
    rep = fit_observations(obs, (rig.width, rig.height), rig.schedule, dense=dense)
    cal = rep.calibration
    np.testing.assert_allclose(cal.camera_matrix, rig.camera_matrix, atol=1e-3)
    r0, t0 = truth[0]
    np.testing.assert_allclose(np.abs(cal.plane_normal @ r0[:, 2]), 1.0, atol=1e-9)
    assert cal.plane_normal @ t0 < 0  # normal points toward the camera
    assert cal.plane_offset_mm == pytest.approx(
        -(cal.plane_normal @ t0), abs=1e-4
    )  # float32 corners
    assert rep.rms_mm < 1e-4
    lo, hi = cal.height_range_mm
    assert lo < 0.0 < 20.0 < hi
    err = _height_error(rig, cal, truth[0], lo, hi)
    assert np.percentile(err, 99) < 2e-4 and err.max() < 5e-3  # max: extrapolated image corners
    assert [p["pose"] for p in cal.pose_residuals] == list(range(len(obs)))
    assert all(p.corners == BOARD.n_points for p in rep.poses)
    assert all((p.points > 500) if dense else (p.points == BOARD.n_points) for p in rep.poses)
    assert {"pose", "corners", "reprojection_px", "rms_mm", "points"} <= set(cal.pose_residuals[0])
    table = rep.table()
    assert "pose_05" in table and "reproj_px" in table and "all" in table


def test_fit_with_corner_noise_stays_accurate(standard_noisy_fit):
    """The package's shared fit (tests/calib/conftest.py) of exactly these observations."""
    rig, rep = standard_noisy_fit
    obs, truth = _observations(rig, noise_px=0.05)
    for mine, shared in zip(obs, standard_noisy_observations(rig), strict=True):
        np.testing.assert_array_equal(mine.image_points, shared.image_points)
        np.testing.assert_array_equal(mine.phase, shared.phase)
    assert 0.02 < rep.reprojection_px < 0.1
    err = _height_error(rig, rep.calibration, truth[0], 0.0, 20.0)
    assert err.mean() < 0.02 and err.max() < 0.1


def test_phase_over_the_boards_refines_camera_and_reference_plane():
    """Corner noise leaves the camera and the nearly fronto-parallel reference board loose; the
    phase over the boards (noise-free here), fitted jointly with them, pulls the heights across
    the field and the focal length toward the truth."""
    rig = Rig()
    obs, truth = _observations(rig, noise_px=0.15)
    rms, focal = {}, {}
    for refine in (False, True):
        cal = fit_observations(
            obs, (rig.width, rig.height), rig.schedule, refine=refine
        ).calibration
        rms[refine] = float(np.sqrt(np.mean(_height_error(rig, cal, truth[0], 0.0, 20.0) ** 2)))
        focal[refine] = abs(cal.camera_matrix[0, 0] - rig.f_px)
    assert rms[True] < 0.75 * rms[False]
    assert focal[True] < focal[False]


def test_the_leave_one_pose_out_joint_refits_weigh_their_residuals_as_the_whole_fit(
    monkeypatch,
):
    """The jackknife repeats the joint (corners + phase) fit with each pose left out, from the
    whole fit's solution: the same weighted problem, so with the whole fit's noise scales. Scales
    estimated again at that solution were the phase's misfit there — on this noise-free phase
    the 1e-4 px floor against the whole fit's ~0.05 px — and each refit crawled along its stiff
    valley to the 100-evaluation limit (MINPACK's status 0; 50 s for this calibration)."""
    from app.calib import refine

    solves: list[tuple[bool, int]] = []
    scales: list[refine.NoiseScales | None] = []
    solve, refine_poses = refine.levenberg_marquardt, refine.refine_board_poses

    def counted(fun, jac, x0, **kwargs):  # type: ignore[no-untyped-def]
        r = solve(fun, jac, x0, **kwargs)  # the joint fit: projector, camera, six per view
        solves.append((r.converged, r.nfev))
        return r

    def recorded(*args, **kwargs):  # type: ignore[no-untyped-def]
        out = refine_poses(*args, **kwargs)
        scales.append(None if out is None else out.noise_scales)
        return out

    monkeypatch.setattr(refine, "levenberg_marquardt", counted)
    monkeypatch.setattr("app.calib.fitting.refine_board_poses", recorded)
    rig = Rig()
    obs, _ = _observations(rig, noise_px=0.15)
    fit_observations(obs, (rig.width, rig.height), rig.schedule, refine=True)
    whole = scales[0]
    assert whole is not None and len(whole.phase_px) == len(obs)
    refits = [s for s in scales[1:] if s is not None and len(s.phase_px) == len(obs) - 1]
    assert len(refits) == len(obs) - 1  # pose 0 left out keeps the whole fit's camera
    for left, s in enumerate(refits, start=1):
        assert s.corner_px == whole.corner_px
        assert s.phase_px == tuple(p for k, p in enumerate(whole.phase_px) if k != left)
    assert len(solves) >= len(obs)
    assert all(converged and nfev <= 30 for converged, nfev in solves), solves


def test_eq5_linear_start_and_lm_recover_coefficients():
    rng = np.random.default_rng(0)
    num = rng.normal(0, 0.1, 11)
    den = np.r_[0.05, rng.normal(0, 0.005, 11)]
    u, v, p = rng.uniform(-1, 1, (3, 500))
    z = evaluate(num, den, u, v, p)
    fit = fit_eq5(u, v, p, z)
    np.testing.assert_allclose(evaluate(fit.numerator, fit.denominator, u, v, p), z, atol=1e-8)
    assert basis(u, v, p).shape == (500, 12)


def test_sample_phase_bilinear_and_refuses_invalid_neighbours():
    vv, uu = np.mgrid[0:20, 0:30].astype(np.float32)
    phase = 0.5 * uu - 0.25 * vv + 3.0
    pts = np.array([[3.25, 4.5], [10.0, 10.0], [28.9, 2.0], [29.5, 2.0], [-0.1, 3.0]])
    out = sample_phase(phase, pts)
    np.testing.assert_allclose(out[:3], 0.5 * pts[:3, 0] - 0.25 * pts[:3, 1] + 3.0, rtol=1e-6)
    assert np.isnan(out[3:]).all()  # outside the 2x2 support
    phase[5, 4] = np.nan
    assert np.isnan(sample_phase(phase, np.array([[3.5, 4.5], [4.2, 5.7]]))).all()
    assert np.isfinite(sample_phase(phase, np.array([[5.5, 4.5]]))).all()


def test_too_few_poses():
    rig = Rig()
    obs, _ = _observations(rig, STANDARD_POSES[:2])
    with pytest.raises(ValueError, match="^poses: need at least 3"):
        fit_observations(obs, (rig.width, rig.height), rig.schedule)


def test_parallel_poses_are_degenerate_tilts():
    rig = Rig()
    poses = [(100.0 - 5 * i, 5.0, 5.0, 0.0, (i, -i)) for i in range(4)]
    obs, _ = _observations(rig, poses)
    with pytest.raises(ValueError, match="degenerate tilts"):
        fit_observations(obs, (rig.width, rig.height), rig.schedule)


def test_poses_without_depth_span():
    rig = Rig()
    poses = [
        (100.0, 2.0, -1.5, 0, (0, 0)),
        (100.1, -2.0, 1.5, 0, (0, 0)),
        (100.0, 1.5, 2.0, 0, (0, 0)),
        (99.9, -1.5, -2.0, 0, (0, 0)),
    ]
    small = BoardSpec("checkerboard", 7, 5, 1.0)
    obs = []
    for i, (d, ax, ay, az, sh) in enumerate(poses):
        r, t = board_pose(small, d, ax, ay, az, sh)
        obs.append(rig.observe(small, r, t, f"pose_{i:02d}"))
    with pytest.raises(ValueError, match="span only"):
        fit_observations(obs, (rig.width, rig.height), rig.schedule)


def test_board_missing_in_pose_zero_and_too_few_found():
    rig = Rig()
    obs, _ = _observations(rig)
    with pytest.raises(ValueError, match="^pose 0: board not found"):
        fit_observations([None, *obs[1:]], (rig.width, rig.height), rig.schedule)
    with pytest.raises(ValueError, match="poses with the board found"):
        fit_observations(
            [obs[0], None, None, None, None, obs[5]], (rig.width, rig.height), rig.schedule
        )


def test_robust_drops_a_pose_with_an_unwrapping_error():
    rig = Rig()
    obs, truth = _observations(rig)
    bad = obs[3]
    # A fringe-order slip over part of pose 3, as a failed unwrapping would give.
    bad.phase = bad.phase.copy()
    bad.phase[:, 330:] += 2 * np.pi
    plain = fit_observations(obs, (rig.width, rig.height), rig.schedule)
    assert plain.rms_mm > 0.05
    rep = fit_observations(obs, (rig.width, rig.height), rig.schedule, robust=True)
    p3 = rep.poses[3]
    assert p3.dropped or p3.dropped_points > 0
    assert rep.rms_mm < 1e-3
    assert _height_error(rig, rep.calibration, truth[0], 0.0, 20.0).max() < 5e-3
    assert "DROPPED" in rep.table() or p3.points < p3.corners


def test_geometric_region_is_verified_per_cell():
    """The calibration gives the geometric model a per-cell height range (32 × 24 cells): exact
    boards verify the calibrated range with its 2 mm margin everywhere (a measured height may
    pass it by the 0.25 mm step) — the leave-one-pose-out fits agree exactly there."""
    rig = Rig()
    obs, _ = _observations(rig)
    cal = fit_observations(
        obs, (rig.width, rig.height), rig.schedule, model="geometric"
    ).calibration
    g = cal.model.region.height_grid_mm
    lo, hi = cal.height_range_mm
    assert g is not None and g.shape == (24, 32, 2)
    assert cal.model.region.cell_px == (rig.width / 32, rig.height / 24)
    np.testing.assert_allclose(g[..., 0], lo - 2.0, atol=1e-6)
    np.testing.assert_allclose(g[..., 1], hi + 2.0, atol=0.25 + 1e-6)  # the height grid's step
    assert cal.model.region.height_allowance_mm == 0.25
    assert cal.model.k1 == 0.0  # the rig's projector is a pinhole; k1's estimate is not significant
