"""The reconstruction thread's bracket step: a map only from two sets of different exposures,
fused per pixel as the CLI fuses them; the acquisition alternates the exposures."""

from __future__ import annotations

import numpy as np
import pytest

from app.devices.base import Frame
from app.devices.sim import SimulatedWorld
from app.devices.sim.ideal import ideal_calibration
from app.recon import Reconstructor
from app.recon.fusion import fuse_exposures
from app.recon.sensor import SensorNoise
from app.service.framesets import FrameSet
from app.service.reconstruction import Reconstruction
from app.service.store import NewestQueue


@pytest.fixture(scope="module")
def bracket() -> tuple[dict[float, np.ndarray], Reconstructor]:
    world = SimulatedWorld("anastomosis", seed=4, distortion=False)
    sets = {
        e: np.stack([world.render(i, 0.0, exposure_ms=e, gain=1.0, bits=8) for i in range(16)])
        for e in (20.0, 80.0)
    }
    return sets, Reconstructor(ideal_calibration(world.rig, world.schedule))


def frame_set(frames: np.ndarray, exposure_ms: float, first_index: int) -> FrameSet:
    return FrameSet(
        tuple(
            Frame(
                frames[p],
                index=first_index + p,
                timestamp=0.03 * (first_index + p),
                pattern_index=p,
                exposure_ms=exposure_ms,
                led="green",
            )
            for p in range(16)
        ),
        0.0,
        "set",
    )


def test_a_pair_of_exposures_makes_one_fused_map(bracket) -> None:
    sets, engine = bracket
    # measuring off: every set with the engine's (nominal) noise model, as compared below
    rec = Reconstruction(NewestQueue(1), lambda: engine, noise_estimate_interval_s=0.0)
    noise = engine.noise or SensorNoise.typical(255)
    assert (
        rec.process_bracket(engine, frame_set(sets[20.0], 20.0, 0)) is None
    )  # waits for its partner
    # a lost set leaves two of one exposure: the newer one waits instead
    assert rec.process_bracket(engine, frame_set(sets[20.0], 20.0, 16)) is None
    fused = rec.process_bracket(engine, frame_set(sets[80.0], 80.0, 32))
    assert fused is not None
    assert fused.bracket_exposures_ms == (20.0, 80.0) and fused.exposure_ms == 20.0
    assert fused.metadata()["bracket_exposures_ms"] == [20.0, 80.0]
    short, long_ = (engine.run(sets[e], noise=noise) for e in (20.0, 80.0))
    want = fuse_exposures([short, long_], [20.0, 80.0]).result
    assert np.array_equal(fused.valid, want.valid) and np.array_equal(fused.reason, want.reason)
    assert np.array_equal(fused.depth, want.depth, equal_nan=True)
    assert fused.valid.sum() > max(short.valid.sum(), long_.valid.sum())
    print(
        f"\nanastomosis (offline render): valid {100 * short.valid.mean():.1f} % at 20 ms, "
        f"{100 * long_.valid.mean():.1f} % at 80 ms, fused {100 * fused.valid.mean():.1f} %"
    )
    # the pair is spent: the next set starts a new one
    assert rec.process_bracket(engine, frame_set(sets[20.0], 20.0, 48)) is None
