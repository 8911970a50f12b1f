"""A live map's points: made from its depth on the first read (as the engine's would be), once;
a map nobody asks points of never makes them."""

from __future__ import annotations

import numpy as np

from app.devices.base import Frame
from app.devices.sim import SimulatedWorld
from app.devices.sim.ideal import ideal_calibration
from app.recon import Reconstructor
from app.recon.motion import MotionTest
from app.recon.points import LazyPoints
from app.recon.sensor import SensorNoise
from app.service.framesets import FrameSet
from app.service.reconstruction import Reconstruction
from app.service.store import NewestQueue


def test_live_points_are_the_engines_made_on_demand() -> None:
    world = SimulatedWorld("plane", seed=4, distortion=False)
    frames = np.stack([world.render(i, 0.0, exposure_ms=20.0, gain=1.0, bits=8)
                       for i in range(16)])
    engine = Reconstructor(ideal_calibration(world.rig, world.schedule),
                           noise=SensorNoise(gain_dn_per_e=255 / 16000, read_noise_dn=0.4))
    fs = FrameSet(tuple(Frame(frames[p], index=p, timestamp=0.03 * p, pattern_index=p,
                              exposure_ms=20.0, led="green") for p in range(16)), 0.0, "set")
    rec = Reconstruction(NewestQueue(1), lambda: engine, motion=MotionTest(grow_px=1))
    live = rec.process(engine, fs)
    assert LazyPoints.given(live) is None and live.point_rays is not None
    assert live.valid.mean() > 0.5
    pts = live.points
    assert live.points is pts
    ref = engine.run(frames, motion=MotionTest(grow_px=1))
    assert np.array_equal(pts, ref.points, equal_nan=True)
    assert np.array_equal(np.isnan(pts).any(axis=-1), ~live.valid)
