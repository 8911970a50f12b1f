"""The Reconstructor API and compute_phase: metric accuracy on the rig, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.core.calibration import Calibration
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import PatternSchedule, Reason, ReconResult, Reconstructor, compute_phase


@pytest.fixture(scope="module")
def rig():
    return Rig()


@pytest.mark.parametrize("fast", [False, True])
def test_depth_and_points_on_the_rig(rig, fast):
    h = bump_surface(rig)
    frames = rig.render(h, background=30000, amplitude=25000, dtype=np.uint16)
    res = Reconstructor(rig.calibration(), fast=fast, with_phase=True).run(frames)
    assert isinstance(res, ReconResult)
    assert res.valid.all()
    assert np.max(np.abs(res.depth - h)) < 1e-3  # mm
    assert np.max(np.abs(res.points - rig.points(h))) < 2e-3  # mm
    assert np.max(np.abs(res.phase - rig.finest_phase(h))) < 2e-3  # rad
    assert res.points.shape == (rig.height, rig.width, 3)
    assert np.allclose(res.texture, 55000, atol=60)
    assert np.allclose(res.modulation, 25000, atol=60)
    assert res.elapsed_ms > 0


def test_noise_propagates_as_theory(rig):
    """Phase RMS of the finest frequency within 10 % of σ_I·√(2/N)/B on real rig frames."""
    h = bump_surface(rig)
    sigma, b = 30.0, 2000.0
    frames = rig.render(h, background=20000, amplitude=b, noise=sigma, dtype=np.uint16,
                        rng=np.random.default_rng(5))
    res = compute_phase(frames, rig.schedule)
    assert (res.reason == 0).all()
    err = res.phase - rig.finest_phase(h)
    theory = sigma * math.sqrt(2 / 4) / b
    assert abs(np.sqrt(np.mean(err**2)) / theory - 1) < 0.10


def test_compute_phase_reasons_only_phase_stage(rig):
    frames = rig.render(bump_surface(rig))
    frames[:, :10, :10] = 100
    res = compute_phase(frames, rig.schedule)
    assert (res.reason[:10, :10] == Reason.LOW_MODULATION).all()
    assert np.isnan(res.phase[:10, :10]).all()
    assert set(np.unique(res.reason)) <= {0, 1, 2, 3}
    assert res.phase.dtype == res.background.dtype == np.float32


def test_bad_frames_raise_naming_frames(rig):
    rec = Reconstructor(rig.calibration(), fast=False)
    good = rig.render(bump_surface(rig))
    cases = [
        good[:15],  # wrong frame count
        good[:, :, :-1],  # wrong image size
        good[0],  # 2-D
        good.astype(np.float32),  # dtype
        [*list(good[:15]), good[15].astype(np.uint16)],  # mixed dtypes
        [*list(good[:15]), good[15, :, :-1]],  # mixed shapes
        "frames",
    ]
    for bad in cases:
        with pytest.raises(ValueError, match="^frames"):
            rec.run(bad)
    assert rec.run(list(good)).valid.any()  # a list of equal frames is fine
    with pytest.raises(ValueError, match="^max_code"):
        Reconstructor(rig.calibration(), max_code=4095).run(good)  # uint8 tops at 255


def test_bad_parameters(rig):
    cal = rig.calibration()
    for kwargs, name in (
        (dict(height_margin_mm=-1.0), "height_margin_mm"),
        (dict(consistency_rad=4.0), "consistency_rad"),
        (dict(min_modulation=float("nan")), "min_modulation"),
        (dict(max_code=0), "max_code"),
    ):
        with pytest.raises(ValueError, match=f"^{name}"):
            Reconstructor(cal, **kwargs)
    with pytest.raises(ValueError, match="^calibration"):
        Reconstructor(object())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^schedule"):
        compute_phase(np.zeros((16, 2, 2), np.uint8), "schedule")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^frames"):
        compute_phase(np.zeros((12, 2, 2), np.uint8), PatternSchedule())


def test_nan_calibration_rejected(rig):
    cal = rig.calibration()
    for field, value in (("numerator", np.full(11, np.nan)),
                         ("denominator", np.r_[np.nan, np.zeros(11)]),
                         ("camera_matrix", np.full((3, 3), np.nan))):
        kwargs = {f: getattr(cal, f) for f in (
            "camera_matrix", "dist_coeffs", "image_size", "plane_normal", "plane_offset_mm",
            "numerator", "denominator", "normalization", "pattern", "height_range_mm")}
        kwargs[field] = value
        with pytest.raises(ValueError, match=f"^{field}"):
            Calibration(**kwargs)


def test_12bit_saturation_needs_max_code(rig):
    frames = rig.render(bump_surface(rig), background=2000, amplitude=1200, dtype=np.uint16,
                        max_code=4095)
    frames[2:4, 50, 60] = 4095  # two of four shifts clipped: φ is undetermined
    frames[5, 20, 30] = 4095  # one clipped: refitted from the other three
    for fast in (True, False):
        res = Reconstructor(rig.calibration(), max_code=4095).run(frames, fast=fast)
        assert res.reason[50, 60] == Reason.SATURATED
        assert res.reason[20, 30] == Reason.OK and res.recovered == 1
    # default 65535: the clipped pixel is not flagged; the modulation rule follows the (16-bit)
    # sensor's noise, not a fraction of full scale, so B = 1200 codes still decodes
    res = Reconstructor(rig.calibration()).run(frames)
    assert res.reason[50, 60] != Reason.SATURATED and res.recovered == 0
    assert not (res.reason == Reason.LOW_MODULATION).any()
    # an explicit threshold wins: 2 % of 65535 rejects everything
    res = Reconstructor(rig.calibration(), min_modulation=0.02 * 65535).run(frames)
    assert (res.reason == Reason.LOW_MODULATION).all()


def test_outputs_are_recycled_only_when_nobody_holds_them(rig):
    import weakref

    frames = rig.render(bump_surface(rig))
    rec = Reconstructor(rig.calibration())
    a = rec.run(frames)
    a_depth = weakref.ref(a.depth)  # ids can repeat after a free; a weak reference cannot lie
    expected = a.depth.copy()
    view = a.depth[::2]  # a view keeps its base (and its result) out of reuse
    del a
    b = rec.run(frames)
    assert a_depth() is not None and b.depth is not a_depth()
    del view
    d = rec.run(frames)  # b is held, a is free again: a's arrays come back, rewritten
    assert d.depth is a_depth() and d.depth is not b.depth
    assert np.array_equal(d.depth, expected, equal_nan=True)
