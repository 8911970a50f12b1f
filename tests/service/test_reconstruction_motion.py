"""The reconstruction step invalidates moved pixels (reason MOTION) in both modes."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.reasons import Reason
from app.devices.base import Frame
from app.devices.sim import SimulatedWorld
from app.devices.sim.ideal import ideal_calibration
from app.recon import Reconstructor
from app.service.framesets import FrameSet
from app.service.motion import sigma_bounds
from app.service.reconstruction import Reconstruction
from app.service.store import NewestQueue


@pytest.fixture(scope="module")
def still_set() -> tuple[np.ndarray, Reconstructor]:
    world = SimulatedWorld("plane", seed=4, distortion=False)
    frames = np.stack([world.render(i, 0.0, exposure_ms=20.0, gain=1.0, bits=8) for i in range(16)])
    return frames, Reconstructor(ideal_calibration(world.rig, world.schedule))


def frame_set(frames: np.ndarray, indices: list[int], mode: str) -> FrameSet:
    return FrameSet(tuple(Frame(frames[p], index=i, timestamp=0.03 * i, pattern_index=p, exposure_ms=20.0, led="green")
                          for p, i in enumerate(indices)), 0.0, mode)


@pytest.mark.parametrize("mode", ["set", "rolling"])
def test_a_patch_that_changed_in_one_group_is_motion_and_the_rest_is_untouched(still_set, mode):
    frames, engine = still_set
    rec = Reconstruction(NewestQueue(1), lambda: engine, n_frequencies=4, motion_grow_px=2)
    still = rec.process(engine, frame_set(frames, list(range(16)), "set"))
    assert still.valid.mean() > 0.5
    # false alarms only: each grows to a 5 × 5 square, so about 25·α of the pixels
    assert still.moved_pixels < 1.3 * 25 * rec.motion_false_alarm_rate * still.valid.size
    assert not still.scene_moved and still.uncertain_moving_pixels == 0  # still: only the engine's σ limit
    moved = frames.copy()
    patch = (slice(400, 460), slice(600, 700))
    moved[4:8][(slice(None), *patch)] = np.clip(moved[4:8][(slice(None), *patch)].astype(int) + 40, 0, 255)
    # rolling: the set after group 1 completes (frames 16..19 hold group 0, 20..23 group 1, then 8..15)
    idx = list(range(16)) if mode == "set" else list(range(16, 24)) + list(range(8, 16))
    res = rec.process(engine, frame_set(moved, idx, mode))
    inner = (slice(402, 458), slice(602, 698))
    lit = still.valid[inner]
    assert (res.reason[inner][lit] == Reason.MOTION).all()
    assert not res.valid[400:460, 600:700].any() or not still.valid[400:460, 600:700].all()
    assert np.isnan(res.depth[inner][lit]).all() and np.isnan(res.points[inner][lit]).all()
    elsewhere = np.ones(res.valid.shape, bool)
    elsewhere[395:465, 595:705] = False
    same = (res.valid == still.valid)[elsewhere].mean()
    assert same > 1.0 - 2 * 1.3 * 25 * rec.motion_false_alarm_rate  # only the two runs' false alarms differ
    assert res.moved_pixels >= 60 * 100 and res.mode == mode
    # 6000 flagged pixels are far beyond a still set's count: the moving-scene σ bound applied
    bound = sigma_bounds(rec.gross_error_mm, 4, rec.motion_false_alarm_rate)[1]
    assert res.scene_moved and np.nanmax(res.sigma[res.valid]) <= bound
    assert res.uncertain_moving_pixels == (still.valid & (still.sigma > bound) & ~res.motion).sum()
    # the map stands for the finest group's mid time: frames 12..15 in either order
    assert res.map_time_s == pytest.approx(0.03 * 13.5)
