"""The reconstruction thread's step: the engine with the measured noise and the motion test."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.reasons import Reason
from app.devices.base import Frame
from app.devices.sim import SimulatedWorld
from app.devices.sim.ideal import ideal_calibration
from app.recon import Reconstructor
from app.recon.motion import MotionTest, sigma_bounds
from app.recon.noise import estimate_sensor_noise
from app.recon.sensor import SensorNoise
from app.service.framesets import FrameSet
from app.service.reconstruction import Reconstruction
from app.service.store import NewestQueue


@pytest.fixture(scope="module")
def still_set() -> tuple[np.ndarray, Reconstructor]:
    world = SimulatedWorld("plane", seed=4, distortion=False)
    frames = np.stack([world.render(i, 0.0, exposure_ms=20.0, gain=1.0, bits=8) for i in range(16)])
    return frames, Reconstructor(ideal_calibration(world.rig, world.schedule))


def frame_set(frames: np.ndarray, indices: list[int], mode: str) -> FrameSet:
    return FrameSet(
        tuple(
            Frame(
                frames[p],
                index=i,
                timestamp=0.03 * i,
                pattern_index=p,
                exposure_ms=20.0,
                led="green",
            )
            for p, i in enumerate(indices)
        ),
        0.0,
        mode,
    )


@pytest.mark.parametrize("mode", ["set", "rolling"])
def test_a_patch_that_changed_in_one_group_is_motion_and_the_rest_is_untouched(still_set, mode):
    frames, engine = still_set
    test = MotionTest(grow_px=2, gross_error_mm=0.5)
    rec = Reconstruction(NewestQueue(1), lambda: engine, motion=test)
    still = rec.process(engine, frame_set(frames, list(range(16)), "set"))
    assert still.valid.mean() > 0.5
    # a still map has any flagged pixel with probability <= α = 1e-4 (over the image)
    assert still.moved_pixels == 0 and not still.motion.any()
    # still: only the engine's σ limit
    assert not still.scene_moved and still.uncertain_moving_pixels == 0
    moved = frames.copy()
    patch = (slice(400, 460), slice(600, 700))
    moved[4:8][(slice(None), *patch)] = np.clip(
        moved[4:8][(slice(None), *patch)].astype(int) + 40, 0, 255
    )
    # rolling: the set after group 1 completes (frames 16..19 hold group 0, 20..23 group 1, then
    # 8..15)
    idx = list(range(16)) if mode == "set" else list(range(16, 24)) + list(range(8, 16))
    res = rec.process(engine, frame_set(moved, idx, mode))
    inner = (slice(402, 458), slice(602, 698))
    lit = still.valid[inner]
    assert (res.reason[inner][lit] == Reason.MOTION).all()
    assert not res.valid[400:460, 600:700].any() or not still.valid[400:460, 600:700].all()
    assert np.isnan(res.depth[inner][lit]).all() and np.isnan(res.points[inner][lit]).all()
    # flagged: the patch, the windows that hold a patch pixel (r = 2) and their growth (2)
    assert not res.motion[:396].any() and not res.motion[464:].any()
    assert not res.motion[:, :596].any() and not res.motion[:, 704:].any()
    assert res.moved_pixels >= 60 * 100 and res.mode == mode
    # the scene moved: the moving-scene σ bound applied, elsewhere nothing else changed
    bound = sigma_bounds(0.5, 4)[1]
    assert res.scene_moved and np.nanmax(res.sigma[res.valid]) <= bound
    elsewhere = np.ones(res.valid.shape, bool)
    elsewhere[395:465, 595:705] = False
    with np.errstate(invalid="ignore"):
        kept = still.valid & ~(still.sigma > bound)
    assert np.array_equal(res.valid[elsewhere], kept[elsewhere])
    assert res.uncertain_moving_pixels == (still.valid & (still.sigma > bound) & ~res.motion).sum()
    # the map stands for the finest group's mid time: frames 12..15 in either order
    assert res.map_time_s == pytest.approx(0.03 * 13.5)


def test_the_measured_noise_is_passed_to_the_engine_not_installed_in_it(still_set):
    frames, engine = still_set
    rec = Reconstruction(NewestQueue(1), lambda: engine, motion=MotionTest())
    first = rec.process(engine, frame_set(frames, list(range(16)), "set"))
    # until the thread measures it, the engine fits the noise to each set itself
    assert rec.noise.current is None and first.noise_source == "set"
    assert first.noise == estimate_sensor_noise(frames, engine.calibration.pattern, max_code=255)
    measured = rec.noise.update(frames, engine.calibration.pattern, 255, 0.0)
    assert measured is not None and measured is rec.noise.current
    res = rec.process(engine, frame_set(frames, list(range(16)), "set"))
    assert res.noise is measured and engine.noise is None
    assert res.noise_source == "given"
    # σ follows the model it was given: σ ∝ √(read² + gain·A)
    nominal = engine.run(frames, noise=SensorNoise.typical(255))
    both = res.valid & nominal.valid
    assert not np.allclose(res.sigma[both], nominal.sigma[both])


def test_with_measuring_off_the_live_thread_keeps_the_nominal_noise(still_set):
    frames, engine = still_set
    rec = Reconstruction(
        NewestQueue(1), lambda: engine, motion=MotionTest(), noise_estimate_interval_s=0.0
    )
    res = rec.process(engine, frame_set(frames, list(range(16)), "set"))
    assert res.noise == SensorNoise.typical(255)


def test_the_pipeline_hands_its_motion_settings_to_the_thread_as_one_test():
    from app.core.schedule import SCHEDULES
    from app.service.pipeline import LivePipeline, PipelineConfig

    config = PipelineConfig(
        exposure_ms=20.0,
        led="green",
        bit_depth=8,
        rolling=False,
        autostart=False,
        motion_false_alarm_rate=1e-3,
        motion_grow_px=3,
        motion_window_px=7,
        gross_error_mm=0.4,
    )
    pipeline = LivePipeline(config, SCHEDULES["paper-16"], None)
    assert pipeline.reconstruction.motion == MotionTest(
        false_alarm_rate=1e-3, window_px=7, grow_px=3, gross_error_mm=0.4
    )
    with pytest.raises(ValueError, match="window_px"):
        LivePipeline(
            PipelineConfig(
                exposure_ms=20.0,
                led="green",
                bit_depth=8,
                rolling=False,
                autostart=False,
                motion_window_px=4,
            ),
            SCHEDULES["paper-16"],
            None,
        )
