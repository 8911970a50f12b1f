"""Every reason code from a constructed case, on both paths; precedence of the codes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from app.core.eq5 import Eq5Model
from app.core.reasons import assign_reasons
from app.devices.sim.analytic_rig import Rig, reason_scene
from app.recon import PRECEDENCE, Reason, Reconstructor


@pytest.fixture(scope="module")
def rig():
    return Rig()


@pytest.mark.parametrize("fast", [False, True])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_each_reason_in_its_patch(rig, fast, dtype):
    frames, h, patches = reason_scene(rig, dtype=dtype)
    rec = Reconstructor(rig.calibration(), max_code=None if dtype == np.uint8 else 4095, fast=fast)
    res = rec.run(frames)
    for name, (rows, cols) in patches.items():
        assert (res.reason[rows, cols] == Reason[name]).all(), name
        assert np.isnan(res.depth[rows, cols]).all() and not res.valid[rows, cols].any()
        assert np.isnan(res.points[rows, cols]).all()
    assert res.valid.mean() > 0.75
    ok = res.valid
    assert np.array_equal(ok, res.reason == Reason.OK)
    assert np.max(np.abs(res.depth[ok] - h[ok])) < 0.1  # 8-bit noise, mm
    assert not np.isnan(res.depth[ok]).any() and not np.isnan(res.points[ok]).any()


@pytest.mark.parametrize("fast", [False, True])
def test_model_singular_column(rig, fast):
    cal = rig.calibration(height_range_mm=(0.0, 100.0))
    u0 = int(cal.normalization["u"][0] + 0.5)
    cal.normalization["u"] = (float(u0), cal.normalization["u"][1])
    denominator = np.zeros(12)
    denominator[2] = 1.0  # denominator u': height = su / (u - u0), singular at u0
    # numerator 1
    cal.model = Eq5Model(np.zeros(11), denominator, cal.normalization, cal.model.region)
    frames = rig.render(np.full((rig.height, rig.width), 10.0))
    res = Reconstructor(cal, height_margin_mm=0.0, fast=fast).run(frames)
    assert (res.reason[:, u0] == Reason.MODEL_SINGULAR).all()
    assert (res.reason[:, :u0] == Reason.OUTSIDE_VOLUME).all()  # negative heights
    assert (res.reason[:, u0 + 1 :] == Reason.OK).all()
    su = cal.normalization["u"][1]
    assert np.allclose(res.depth[:, u0 + 1 :], su / np.arange(1, rig.width - u0), rtol=1e-5)


def test_precedence_all_combinations():
    names = [
        "saturated",
        "low_modulation",
        "inconsistent",
        "singular",
        "outside",
        "outside_field",
        "uncertain",
        "motion",
    ]
    codes = [
        Reason.SATURATED,
        Reason.LOW_MODULATION,
        Reason.UNWRAP_INCONSISTENT,
        Reason.MODEL_SINGULAR,
        Reason.OUTSIDE_VOLUME,
        Reason.OUTSIDE_FIELD,
        Reason.UNCERTAIN,
        Reason.MOTION,
    ]
    for flags in itertools.product([False, True], repeat=8):
        out = assign_reasons((1,), **{n: np.array([f]) for n, f in zip(names, flags, strict=True)})
        expected = next(
            (c for c in PRECEDENCE if c == Reason.OK or flags[codes.index(c)]), Reason.OK
        )
        assert out[0] == expected, flags
