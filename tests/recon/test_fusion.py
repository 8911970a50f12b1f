"""Exposure-bracket fusion (app.recon.fusion): constructed results, then a rig scene too bright
for one exposure and too dim for the other."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.reasons import Reason
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor
from app.recon.fusion import fuse_exposures
from app.recon.reconstructor import ReconResult


def _result(depth, sigma, reason, modulation, *, phase=True):
    depth = np.asarray(depth, np.float32)
    reason = np.asarray(reason, np.uint8)
    valid = reason == Reason.OK
    shape = depth.shape
    return ReconResult(
        depth=np.where(valid, depth, np.nan).astype(np.float32),
        points=np.where(valid[..., None], np.stack([depth] * 3, axis=-1), np.nan).astype(
            np.float32
        ),
        valid=valid,
        reason=reason,
        modulation=np.asarray(modulation, np.float32),
        texture=np.asarray(modulation, np.float32) * 2,
        phase=np.where(valid, depth, np.nan).astype(np.float32) if phase else None,
        elapsed_ms=1.0,
        sigma=np.where(valid, sigma, np.nan).astype(np.float32),
        recovered=1 if shape else 0,
    )


OK, LOW, SAT, UNC = Reason.OK, Reason.LOW_MODULATION, Reason.SATURATED, Reason.UNCERTAIN


def test_each_pixel_comes_from_the_valid_member_with_the_smallest_sigma():
    short = _result([[1, 2, 3, 4, 5]], [[0.01, 0.05, 0.01, 0.0, 0.0]], [[OK, OK, OK, LOW, SAT]],
                    [[40, 10, 50, 1, 0]])
    long = _result([[9, 8, 7, 6, 5]], [[0.02, 0.02, 0.0, 0.03, 0.0]], [[OK, OK, SAT, OK, SAT]],
                   [[160, 40, 0, 4, 0]])
    fused = fuse_exposures([short, long], [10.0, 40.0])
    r = fused.result
    np.testing.assert_array_equal(fused.member, [[0, 1, 0, 1, -1]])
    np.testing.assert_array_equal(r.depth[0, :4], [1, 8, 3, 6])
    np.testing.assert_allclose(r.sigma[0, :4], [0.01, 0.02, 0.01, 0.03])
    np.testing.assert_array_equal(r.valid, [[True, True, True, True, False]])
    np.testing.assert_array_equal(r.reason, [[OK, OK, OK, OK, SAT]])
    np.testing.assert_array_equal(r.points[0, 1], [8, 8, 8])
    np.testing.assert_array_equal(r.phase[0, :4], [1, 8, 3, 6])
    # modulation and texture in the first member's codes: the long exposure's divided by 4
    np.testing.assert_allclose(r.modulation[0, :4], [40, 10, 50, 1])
    np.testing.assert_allclose(r.texture[0, :4], [80, 20, 100, 2])
    assert np.isnan(r.depth[0, 4]) and np.isnan(r.sigma[0, 4])
    assert r.elapsed_ms == 2.0 and r.recovered == 2
    assert (
        fused.valid_from(0) == 2 and fused.valid_from(1) == 2 and fused.exposures_ms == (10.0, 40.0)
    )


def test_a_pixel_no_member_validates_keeps_the_reason_of_the_member_that_saw_it_best():
    # short: too dim (LOW, 2 codes); long: 16 codes at 4x (4 in the short one's codes) but
    # UNCERTAIN -> the long one's reason
    short = _result([[0, 0]], [[0, 0]], [[LOW, LOW]], [[2, 3]])
    long = _result([[0, 0]], [[0, 0]], [[UNC, SAT]], [[16, 0]])
    r = fuse_exposures([short, long], [10.0, 40.0]).result
    # a clipped member never wins by modulation
    np.testing.assert_array_equal(r.reason, [[UNC, LOW]])
    np.testing.assert_allclose(r.modulation, [[4, 3]])
    assert not r.valid.any()


def test_one_member_is_itself():
    a = _result([[1, 2]], [[0.01, 0.02]], [[OK, LOW]], [[10, 1]])
    r = fuse_exposures([a], [20.0]).result
    np.testing.assert_array_equal(r.depth, a.depth)
    np.testing.assert_array_equal(r.reason, a.reason)


@pytest.mark.parametrize(
    ("results", "exposures", "name"),
    [
        ([], [], "results"),
        ([_result([[1]], [[0.1]], [[OK]], [[9]])], [10.0, 20.0], "exposures_ms"),
        ([_result([[1]], [[0.1]], [[OK]], [[9]])], [0.0], "exposures_ms"),
        (
            [
                _result([[1]], [[0.1]], [[OK]], [[9]]),
                _result([[1, 2]], [[0.1, 0.1]], [[OK, OK]], [[9, 9]]),
            ],
            [10.0, 20.0],
            "image sizes",
        ),
        (
            [
                _result([[1]], [[0.1]], [[OK]], [[9]]),
                _result([[1]], [[0.1]], [[OK]], [[9]], phase=False),
            ],
            [10.0, 20.0],
            "phase",
        ),
    ],
)
def test_bad_input_names_the_argument(results, exposures, name):
    with pytest.raises(ValueError, match=name):
        fuse_exposures(results, exposures)


def test_a_scene_beyond_one_exposure_is_measured_by_the_bracket():
    """Left half white, right half 1/40 as bright. At 10 ms the right half is too dim to measure;
    at 40 ms the left half clips in every shift. Fused, both halves have depth, each with the
    σ and error of the exposure that measured it."""
    rig = Rig()
    h = bump_surface(rig)
    # 1/40: at 40 ms the dim half stands above the rule with the set's own noise (0.68 DN here;
    # at 1/50 only 97 % did, the nominal model's 0.51 DN had made it look measurable)
    albedo = np.where(np.arange(rig.width) < rig.width // 2, 1.0, 0.025)[None, :] * np.ones(
        (rig.height, 1)
    )
    rec = Reconstructor(rig.calibration(), with_phase=True)
    results, bright = [], albedo > 0.5
    for exposure_ms, seed in ((10.0, 1), (40.0, 2)):
        gain = exposure_ms / 10.0
        frames = rig.render(
            h,
            background=110.0 * gain * albedo,
            amplitude=90.0 * gain * albedo,
            noise=0.6,
            rng=np.random.default_rng(seed),
        )
        results.append(rec.run(frames))
    short, long = results
    assert short.valid[bright].mean() > 0.99 and short.valid[~bright].mean() < 0.05
    assert long.valid[bright].mean() == 0.0 and long.valid[~bright].mean() > 0.99
    assert (long.reason[bright] == Reason.SATURATED).all()
    fused = fuse_exposures(results, [10.0, 40.0])
    r = fused.result
    assert r.valid.mean() > 0.99
    assert (fused.member[bright & r.valid] == 0).all() and (
        fused.member[~bright & r.valid] == 1
    ).all()
    err = (r.depth - h)[r.valid]
    assert np.abs(err).max() < 0.5  # no gross error, and each pixel's σ describes its error
    assert 0.8 < np.sqrt(np.mean((err / r.sigma[r.valid]) ** 2)) < 1.25
    # the dim half's σ is the long exposure's own
    np.testing.assert_array_equal(r.sigma[~bright & r.valid], long.sigma[~bright & r.valid])
