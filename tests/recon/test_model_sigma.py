"""The calibration's own σ per pixel and height (σ_model) and the total σ = noise ⊕ model."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from app.batch.setjob import ReconOptions, SetReconstruction, output_files
from app.calib.model import undistort_points
from app.capture.ply import read_ply
from app.core.calibration import Calibration
from app.core.eq5 import Eq5Model
from app.core.geometric import MODEL_SIGMA_TOLERANCE_MM
from app.core.reasons import Reason
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor
from app.recon.reconstructor import SensorNoise
from app.recon.validity import max_depth_sigma_mm
from tests.helpers.analytic_models import band_fitted_calibration

NOISE = SensorNoise(0.5, 4.0)


@pytest.fixture(scope="module")
def fitted() -> tuple[Rig, Calibration]:
    """A geometric model fitted to noisy board samples in a band of heights: a real jackknife."""
    rig, cal = band_fitted_calibration(seed=7)
    assert len(cal.model.jackknife) >= 3 and cal.model.alternative is not None
    return rig, cal


def _direct_sigma(cal: Calibration, u: np.ndarray, v: np.ndarray, h: np.ndarray) -> np.ndarray:
    rays = undistort_points(
        np.stack([u, v], 1).astype(np.float64), cal.camera_matrix, cal.dist_coeffs
    )
    return cal.model.height_sigma(
        u.astype(np.float64), v.astype(np.float64), rays, h, cal.reference_plane
    )


def test_model_sigma_limit_is_the_gross_error_rule():
    assert pytest.approx(max_depth_sigma_mm(), rel=1e-12) == MODEL_SIGMA_TOLERANCE_MM


def test_table_matches_the_jackknife_sigma(fitted):
    rig, cal = fitted
    rec = Reconstructor(cal)
    table = rec.model_sigma
    assert table is not None
    rng = np.random.default_rng(1)
    u = rng.integers(0, rig.width, 3000)
    v = rng.integers(0, rig.height, 3000)
    lo, hi = cal.height_range_mm
    h = rng.uniform(lo - 2.0, hi + 2.0, 3000)
    hm = np.full((rig.height, rig.width), np.nan, np.float32)
    hm[v, u] = h
    got = table.sigma_mm(hm)[v, u]
    want = _direct_sigma(cal, u, v, hm[v, u].astype(np.float64))
    assert np.median(want) > 1e-4  # a real uncertainty, not zero
    # within 2 % + 0.2 µm (rows are banded, columns interpolated, the height a quartic)
    assert np.mean(np.abs(got - want) <= 0.02 * want + 2e-4) > 0.99
    assert np.all(np.isnan(table.sigma_mm(np.full_like(hm, np.nan))))


def test_saved_calibration_keeps_the_uncertainty(fitted, tmp_path):
    rig, cal = fitted
    back = Calibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert len(back.model.jackknife) == len(cal.model.jackknife)
    u = np.array([10.0, rig.width / 2, rig.width - 10.0])
    v = np.array([10.0, rig.height / 2, rig.height - 10.0])
    h = np.array([3.0, 15.0, 28.0])
    np.testing.assert_allclose(_direct_sigma(back, u, v, h), _direct_sigma(cal, u, v, h), rtol=1e-9)
    bare = cal.to_dict()
    del (
        bare["model"]["jackknife"],
        bare["model"]["alternative"],
    )  # a file from before: σ_model unknown
    assert Reconstructor(Calibration.from_dict(bare)).model_sigma is None


def test_eq5_phase_at_inverts_height_at():
    rig = Rig()
    cal = rig.calibration()
    model = cal.model
    assert isinstance(model, Eq5Model)
    rng = np.random.default_rng(2)
    u, v = rng.uniform(0, rig.width, 50), rng.uniform(0, rig.height, 50)
    h = rng.uniform(0.0, 30.0, 50)
    rays = np.zeros((50, 2))
    phi = model.phase_at(u, v, rays, h, cal.reference_plane)
    np.testing.assert_allclose(model.height_at(u, v, rays, phi, cal.reference_plane), h, atol=1e-9)


@pytest.mark.parametrize("fast", [True, False])
def test_total_sigma_is_noise_and_model_in_quadrature(fitted, fast):
    """The same frames with and without the calibration's jackknife: the σ² difference is the
    jackknife variance at each pixel's measured height."""
    rig, cal = fitted
    bare = Calibration.from_dict(
        {
            **cal.to_dict(),
            "model": {
                k: v
                for k, v in cal.model.to_dict().items()
                if k not in ("jackknife", "alternative")
            },
        }
    )
    frames = rig.render(bump_surface(rig), background=110.0, amplitude=90.0, noise=1.0)
    with_model = Reconstructor(cal, noise=NOISE).run(frames, fast=fast)
    noise_only = Reconstructor(bare, noise=NOISE).run(frames, fast=fast)
    ok = with_model.valid & noise_only.valid
    assert ok.mean() > 0.5  # the rest: beyond the boards' phase range (OUTSIDE_FIELD in both)
    assert np.all(with_model.valid <= noise_only.valid)  # the model's σ only ever takes pixels away
    np.testing.assert_array_equal(noise_only.sigma_model[ok], 0.0)
    vv, uu = np.nonzero(ok)
    pick = np.random.default_rng(3).choice(len(vv), 2000, replace=False)
    vv, uu = vv[pick], uu[pick]
    direct = _direct_sigma(cal, uu, vv, with_model.depth[vv, uu].astype(np.float64))
    var_diff = (
        with_model.sigma[vv, uu].astype(np.float64) ** 2
        - noise_only.sigma[vv, uu].astype(np.float64) ** 2
    )
    np.testing.assert_allclose(np.sqrt(np.maximum(var_diff, 0.0)), direct, rtol=0.05, atol=5e-4)
    np.testing.assert_allclose(with_model.sigma_model[vv, uu], direct, rtol=0.02, atol=2e-4)
    np.testing.assert_allclose(
        with_model.sigma_noise[ok], noise_only.sigma[ok], rtol=2e-3, atol=1e-5
    )


def test_fast_and_numpy_agree_with_the_model_sigma(fitted):
    rig, cal = fitted
    frames = rig.render(bump_surface(rig), background=110.0, amplitude=90.0, noise=1.0)
    rec = Reconstructor(cal, noise=NOISE)
    a, b = rec.run(frames), rec.run(frames, fast=False)
    assert (a.valid == b.valid).mean() > 0.9999
    ok = a.valid & b.valid
    np.testing.assert_allclose(a.sigma[ok], b.sigma[ok], rtol=1e-4)


@pytest.mark.parametrize("fast", [True, False])
def test_model_sigma_beyond_the_rule_is_outside_the_field_else_uncertain(fitted, fast):
    """With a σ limit between the model's σ at different pixels: a pixel whose σ_model fails it is
    OUTSIDE_FIELD; one whose σ_model passes but whose total fails is UNCERTAIN."""
    rig, cal = fitted
    frames = rig.render(bump_surface(rig), background=110.0, amplitude=90.0, noise=1.0)
    free = Reconstructor(cal, noise=NOISE).run(frames, fast=fast)
    sm = free.sigma_model[free.valid]
    limit = float(np.percentile(sm, 70))  # σ_model fails it on ~30 % of the pixels
    res = Reconstructor(cal, noise=NOISE, max_sigma_mm=limit).run(frames, fast=fast)
    was = free.valid
    model_fails = free.sigma_model > limit * 1.001
    total_fails = (free.sigma > limit * 1.001) & (free.sigma_model < limit * 0.999)
    assert model_fails[was].mean() > 0.2 and total_fails[was].any()
    assert np.all(res.reason[was & model_fails] == Reason.OUTSIDE_FIELD)
    assert np.all(res.reason[was & total_fails] == Reason.UNCERTAIN)
    assert np.all(res.sigma[res.valid] <= limit)


def test_outputs_write_both_parts(fitted, tmp_path):
    rig, cal = fitted
    frames = rig.render(bump_surface(rig), background=110.0, amplitude=90.0, noise=1.0)
    res = Reconstructor(cal, noise=NOISE).run(frames)
    files = output_files(
        SetReconstruction(res, None, (20.0,), True),
        ReconOptions(),
        ("sigma.npy", "sigma_noise.npy", "sigma_model.npy", "points.ply"),
    )
    sig, noise, model = (
        np.load(io.BytesIO(files[n])) for n in ("sigma.npy", "sigma_noise.npy", "sigma_model.npy")
    )
    ok = res.valid
    assert np.array_equal(np.isfinite(noise), ok) and np.array_equal(np.isfinite(model), ok)
    np.testing.assert_allclose(sig[ok] ** 2, noise[ok] ** 2 + model[ok] ** 2, rtol=1e-4)
    assert np.median(model[ok]) > 0.0
    (tmp_path / "points.ply").write_bytes(files["points.ply"])
    cloud = read_ply(tmp_path / "points.ply")
    np.testing.assert_array_equal(cloud["sigma_mm"], sig[ok])
    np.testing.assert_array_equal(cloud["sigma_noise_mm"], noise[ok])
    np.testing.assert_array_equal(cloud["sigma_model_mm"], model[ok])
