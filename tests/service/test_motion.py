from __future__ import annotations

import numpy as np
import pytest

from app.recon.patterns import PatternSchedule, fringe_profile
from app.service.motion import motion_mask


def fringe_set(background: np.ndarray, schedule: PatternSchedule) -> np.ndarray:
    """(16, H, W) uint8 with background A per frequency given as (K, H, W)."""
    k, h, w = background.shape
    cols = np.linspace(0, schedule.width - 1, w)
    out = []
    for fi in range(k):
        for n in range(schedule.steps):
            prof = fringe_profile(schedule, fi, n, columns=cols)[None, :]
            out.append(background[fi] + 40.0 * (prof - 0.5))
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def test_still_scene_has_no_motion_and_a_moved_patch_is_found():
    s = PatternSchedule()
    bg = np.full((4, 30, 50), 100.0)
    assert not motion_mask(fringe_set(bg, s), 4, full_scale=255).any()
    bg[2:, 10:20, 20:30] = 160.0  # the scene changed after the second frequency
    mask = motion_mask(fringe_set(bg, s), 4, full_scale=255)
    assert mask[10:20, 20:30].all() and mask.sum() == 100


def test_noise_below_the_floor_is_not_motion():
    s = PatternSchedule()
    rng = np.random.default_rng(1)
    frames = fringe_set(np.full((4, 30, 50), 80.0), s).astype(np.float64)
    frames += rng.normal(0, 2.0, frames.shape)
    assert motion_mask(np.clip(frames, 0, 255).astype(np.uint8), 4, full_scale=255).mean() < 0.001


def test_invalid_arguments():
    with pytest.raises(ValueError, match="frames"):
        motion_mask(np.zeros((16, 4), np.uint8), 4, full_scale=255)
    with pytest.raises(ValueError, match="n_frequencies"):
        motion_mask(np.zeros((16, 4, 4), np.uint8), 3, full_scale=255)
