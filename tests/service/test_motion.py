from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest

from app.core.reasons import Reason
from app.recon.patterns import PatternSchedule, fringe_profile
from app.recon.reconstructor import SensorNoise
from app.service.motion import (
    group_mid_times,
    invalidate_motion,
    map_time,
    motion_k,
    motion_mask,
    newest_group,
    scene_moved,
    sigma_bounds,
)

NOISE = SensorNoise(gain_dn_per_e=0.5, read_noise_dn=2.0)


def fringe_set(background: np.ndarray, schedule: PatternSchedule, *, modulation: float = 40.0,
               noise: SensorNoise | None = None, seed: int = 0) -> np.ndarray:
    """(F, H, W) uint8 fringe set with background A per group given as (G, H, W), plus sensor noise."""
    g, h, w = background.shape
    cols = np.linspace(0, schedule.width - 1, w)
    rng = np.random.default_rng(seed)
    out = []
    for fi in range(g):
        for n in range(schedule.steps):
            prof = fringe_profile(schedule, fi, n, columns=cols)[None, :]
            img = background[fi] + modulation * (prof - 0.5) * 2.0
            if noise is not None:
                # σ_I² = read² + gain·I; rounding adds the 1/12 DN² the read term already holds
                var = np.maximum(noise.read_noise_dn**2 - 1.0 / 12.0 + noise.gain_dn_per_e * img, 0.0)
                img = img + rng.standard_normal(img.shape) * np.sqrt(var)
            out.append(img)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def test_k_is_the_gaussian_quantile_of_the_bonferroni_level():
    assert motion_k(2, 0.05) == pytest.approx(1.959964, abs=1e-6)  # one two-sided test at 5 %
    assert motion_k(4, 0.06) == pytest.approx(2.326348, abs=1e-6)  # three tests at 2 % each
    with pytest.raises(ValueError, match="n_groups"):
        motion_k(1)
    with pytest.raises(ValueError, match="false_alarm_rate"):
        motion_k(4, 0.0)


@pytest.mark.parametrize("frequencies, steps", [((1, 4, 12, 36), 4), ((1, 6, 36), 3)])
@pytest.mark.parametrize("rate", [1e-2, 1e-3])
def test_false_alarm_rate_on_still_noisy_frames_matches_the_stated_rate(frequencies, steps, rate):
    s = PatternSchedule(frequencies=frequencies, steps=steps)
    g = len(frequencies)
    h, w = 300, 600
    # backgrounds from dark to bright (the noise grows with intensity: the model must follow)
    bg = np.broadcast_to(np.linspace(60.0, 190.0, h)[:, None], (g, h, w)).copy()
    frames = fringe_set(bg, s, noise=NOISE, seed=int(rate * 1e4) + g)
    got = motion_mask(frames, g, noise=NOISE, false_alarm_rate=rate).mean()
    # Bonferroni over tests that share the newest group: at most α, not far below it
    n = h * w
    assert got <= rate + 4 * math.sqrt(rate / n), got
    assert got >= 0.5 * rate, got


def test_a_wrong_noise_model_is_visible_in_the_rate():
    s = PatternSchedule()
    bg = np.full((4, 200, 400), 120.0)
    frames = fringe_set(bg, s, noise=NOISE, seed=3)
    underestimated = SensorNoise(gain_dn_per_e=0.1, read_noise_dn=1.0)
    assert motion_mask(frames, 4, noise=underestimated, false_alarm_rate=1e-3).mean() > 0.05


@pytest.mark.parametrize("moved_group, newest", [(2, -1), (0, 0), (3, 0)])
def test_a_moved_group_is_detected(moved_group, newest):
    s = PatternSchedule()
    bg = np.full((4, 60, 80), 100.0)
    bg[moved_group, 10:30, 20:50] += 60.0  # 12 σ of the difference: the patch's background changed in one group
    frames = fringe_set(bg, s, noise=NOISE, seed=5)
    mask = motion_mask(frames, 4, noise=NOISE, newest=newest, false_alarm_rate=1e-4)
    assert mask[10:30, 20:50].all()
    outside = np.ones_like(mask)
    outside[10:30, 20:50] = False
    assert mask[outside].sum() <= 2  # rate 1e-4 of 4200 pixels


def test_a_change_below_the_noise_is_not_motion():
    s = PatternSchedule()
    bg = np.full((4, 100, 200), 100.0)
    bg[1:] += 1.0  # σ of a group mean here is √(4 + 50)/2 ≈ 3.7 DN: one DN is noise
    frames = fringe_set(bg, s, noise=NOISE, seed=6)
    assert motion_mask(frames, 4, noise=NOISE, false_alarm_rate=1e-4).mean() < 1e-3


def test_invalidate_marks_moved_pixels_in_place_except_saturated():
    s = PatternSchedule()
    h, w = 40, 50
    bg = np.full((4, h, w), 100.0)
    bg[3, :10, :10] = 160.0
    frames = fringe_set(bg, s)
    depth = np.full((h, w), 5.0, np.float32)
    sigma = np.full((h, w), 0.01, np.float32)
    points = np.ones((h, w, 3), np.float32)
    valid = np.ones((h, w), bool)
    reason = np.zeros((h, w), np.uint8)
    reason[:2, :2] = Reason.SATURATED
    valid[:2, :2] = False
    mask, n, _, _ = invalidate_motion(frames, 4, noise=NOISE, depth=depth, points=points, valid=valid, reason=reason,
                                sigma=sigma, grow_px=0)
    assert n == 100 and mask[:10, :10].all() and mask.sum() == 100
    assert (reason[:2, :2] == Reason.SATURATED).all()
    moved = mask.copy()
    moved[:2, :2] = False
    assert (reason[moved] == Reason.MOTION).all() and not valid[mask].any()
    assert np.isnan(depth[moved]).all() and np.isnan(sigma[moved]).all() and np.isnan(points[moved]).all()
    assert (depth[~mask] == 5.0).all() and valid[~mask].all() and (reason[~mask] == 0).all()


def test_moved_regions_grow_by_grow_px():
    s = PatternSchedule()
    bg = np.full((4, 40, 50), 100.0)
    bg[0, 10:20, 30:35] = 160.0
    bg[0, 0, 0] = 160.0  # at the corner the square is cut by the image edge
    frames = fringe_set(bg, s)
    raw = motion_mask(frames, 4, noise=NOISE)
    grown = motion_mask(frames, 4, noise=NOISE, grow_px=2)
    assert raw.sum() == 51
    expected = np.zeros_like(raw)
    expected[8:22, 28:37] = True
    expected[:3, :3] = True
    assert np.array_equal(grown, expected)
    z = np.zeros((40, 50), np.float32)
    mask, n, _, _ = invalidate_motion(frames, 4, noise=NOISE, depth=z.copy(), points=np.zeros((40, 50, 3), np.float32),
                                valid=np.ones((40, 50), bool), reason=z.astype(np.uint8), sigma=z.copy(), grow_px=2)
    assert np.array_equal(mask, expected) and n == expected.sum()
    with pytest.raises(ValueError, match="grow_px"):
        motion_mask(frames, 4, noise=NOISE, grow_px=-1)


def test_invalid_arguments():
    with pytest.raises(ValueError, match="frames"):
        motion_mask(np.zeros((16, 4), np.uint8), 4, noise=NOISE)
    with pytest.raises(ValueError, match="frames"):
        motion_mask(np.zeros((16, 4, 4), np.float32), 4, noise=NOISE)
    with pytest.raises(ValueError, match="n_groups"):
        motion_mask(np.zeros((16, 4, 4), np.uint8), 3, noise=NOISE)
    with pytest.raises(ValueError, match="newest"):
        motion_mask(np.zeros((16, 4, 4), np.uint8), 4, noise=NOISE, newest=4)
    z = np.zeros((4, 4), np.float32)
    with pytest.raises(ValueError, match="points"):
        invalidate_motion(np.zeros((16, 4, 4), np.uint8), 4, noise=NOISE, depth=z, points=z, valid=z > 0,
                          reason=z.astype(np.uint8), sigma=z)


def test_group_times_and_the_map_instant():
    t = np.arange(16) * 0.03  # frames 30 ms apart, capture-set order
    assert group_mid_times(t, 4) == pytest.approx([0.045, 0.165, 0.285, 0.405])
    assert map_time(t, (1, 4, 12, 36), combined=False) == pytest.approx(0.405)  # the finest group
    w = np.array([1, 16, 144, 1296], float)
    assert map_time(t, (1, 4, 12, 36), combined=True) == pytest.approx((w * [0.045, 0.165, 0.285, 0.405]).sum() / w.sum())
    # rolling: the newest group is group 0 (frames 16..19 after 4..15)
    idx = list(range(16, 20)) + list(range(4, 16))
    assert newest_group(idx, 4) == 0 and newest_group(list(range(9)), 3) == 2


def test_sigma_bounds_are_the_tolerance_over_the_noise_and_motion_quantiles():
    still, moving = sigma_bounds(0.5, 4, 1e-4)
    z = 4.891638  # Φ⁻¹(1 − 1e-6 / 2)
    k = 4.149410  # Φ⁻¹(1 − 1e-4 / 6): three tests against the newest group
    assert still == pytest.approx(0.5 / z, rel=1e-5)
    assert moving == pytest.approx(0.5 / (z + k), rel=1e-5)
    # a Gaussian pixel at the still bound exceeds the tolerance at the stated rate 1e-6
    assert 2 * NormalDist().cdf(-0.5 / still) == pytest.approx(1e-6, rel=1e-4)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="gross_error_mm"):
            sigma_bounds(bad, 4)


def test_scene_moved_holds_its_level_on_poisson_counts_and_sees_motion():
    rng = np.random.default_rng(11)
    alpha = 1e-2
    for n_px in (2_000, 100_000, 1_400_000):
        counts = rng.poisson(n_px * alpha, 20_000)
        rate = np.mean([scene_moved(int(c), n_px, alpha) for c in counts])
        assert rate <= alpha, (n_px, rate)  # a still scene is called moving at most at level α
    assert scene_moved(3 * 1_400_000 // 1000, 1_400_000, 1e-4)  # 3e-3 flagged: 30 × the still rate
    assert not scene_moved(140, 1_400_000, 1e-4)
    with pytest.raises(ValueError, match="n_pixels"):
        scene_moved(1, 0)
    with pytest.raises(ValueError, match="false_alarm_rate"):
        scene_moved(1, 10, 1.0)


@pytest.mark.parametrize("moving", [False, True])
def test_the_moving_scene_sigma_bound_applies_only_when_the_scene_moved(moving):
    s = PatternSchedule()
    h, w = 60, 80
    bg = np.full((4, h, w), 100.0)
    if moving:
        bg[3, :10, :10] = 160.0  # 100 flagged pixels: far above a still 4800-pixel set's ≈ 0.5
    frames = fringe_set(bg, s, noise=NOISE, seed=8)
    still_bound, moving_bound = sigma_bounds(0.5, 4)
    sigma = np.full((h, w), 0.5 * (still_bound + moving_bound), np.float32)  # between the two bounds
    sigma[:, w // 2:] = 0.5 * moving_bound  # well inside both
    depth = np.full((h, w), 3.0, np.float32)
    valid = np.ones((h, w), bool)
    reason = np.zeros((h, w), np.uint8)
    mp = invalidate_motion(frames, 4, noise=NOISE, depth=depth, points=np.zeros((h, w, 3), np.float32), valid=valid,
                           reason=reason, sigma=sigma, grow_px=0, gross_error_mm=0.5)
    assert mp.scene_moved == moving
    left = np.zeros((h, w), bool)
    left[:, : w // 2] = True
    if moving:
        assert (reason[left & ~mp.mask] == Reason.UNCERTAIN).all() and not valid[left].any()
        assert np.isnan(depth[left]).all() and mp.uncertain == (left & ~mp.mask).sum()
    else:
        assert mp.uncertain == 0
    keep = ~left & ~mp.mask
    assert valid[keep].all() and (reason[keep] == 0).all() and (depth[keep] == 3.0).all()
    # without a tolerance nothing is bounded
    valid[:] = True
    reason[:] = 0
    mp = invalidate_motion(frames, 4, noise=NOISE, depth=depth, points=np.zeros((h, w, 3), np.float32), valid=valid,
                           reason=reason, sigma=np.full((h, w), 1.0, np.float32), grow_px=0)
    assert mp.uncertain == 0 and not (reason == Reason.UNCERTAIN).any()


def test_clipped_pixels_are_not_tested():
    # a still, over-exposed patch: each frequency's clipped sinusoid has its own mean (the clipping
    # depends on the phase), so its groups' backgrounds disagree although nothing moved
    s = PatternSchedule()
    bg = np.full((4, 40, 600), 100.0)
    bg[:, 10:30, 100:500] = 200.0
    quiet = SensorNoise(gain_dn_per_e=0.02, read_noise_dn=0.5)
    frames = fringe_set(bg, s, modulation=200.0, noise=quiet, seed=9)
    clipped = (frames == 255).any(axis=0)
    assert clipped[10:30, 100:500].mean() > 0.5
    assert motion_mask(frames, 4, noise=quiet, max_code=255)[clipped].sum() == 0
    # the bias is there: tested as if unclipped (a higher clipping code), many are flagged
    frames16 = frames.astype(np.uint16)
    assert motion_mask(frames16, 4, noise=quiet, max_code=4095)[clipped].mean() > 0.05
    with pytest.raises(ValueError, match="max_code"):
        motion_mask(frames, 4, noise=quiet, max_code=300)
