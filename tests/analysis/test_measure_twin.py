"""The noise model the measurements assume, checked on the twin: a pixel's phase noise is
independent of its neighbours' (so box means and many-pixel sums may add variances)."""

from __future__ import annotations

import numpy as np
import pytest

from app.devices.sim import render_capture_set
from app.devices.sim.world import SimulatedWorld
from app.recon import compute_phase


@pytest.mark.slow
def test_phase_noise_is_uncorrelated_between_neighbouring_pixels() -> None:
    world = SimulatedWorld("intestine_flap", seed=3, rig="default")
    phases = []
    for seed in (100, 101):  # the same surface, two sensor-noise realisations
        world.reseed(seed)
        cs, _, _ = render_capture_set(world.scene, world=world, exposure_ms=30.0)
        phases.append(
            np.asarray(
                compute_phase(cs.frames, cs.schedule, max_code=cs.max_code).phase, np.float64
            )
        )
    d = phases[0] - phases[1]
    ok = np.isfinite(d) & (np.abs(d) < 1.0)  # noise, not a 2π unwrapping slip
    d = np.where(ok, d - d[ok].mean(), np.nan)
    assert ok.mean() > 0.3

    def corr(du: int, dv: int) -> float:
        a, b = d[: d.shape[0] - dv, : d.shape[1] - du], d[dv:, du:]
        m = np.isfinite(a) & np.isfinite(b)
        return float(np.corrcoef(a[m], b[m])[0, 1])

    # ~10⁶ pixel pairs: a correlation of 0.01 would stand out at 10 standard errors
    for lag in ((1, 0), (0, 1), (1, 1), (2, 0), (0, 2), (3, 0)):
        assert abs(corr(*lag)) < 0.01, lag
    # the same statistic does see correlated noise: a 2-px box blur of it
    import cv2

    blurred = cv2.blur(np.nan_to_num(d), (2, 2))
    a, b = blurred[:, :-1][ok[:, :-1] & ok[:, 1:]], blurred[:, 1:][ok[:, :-1] & ok[:, 1:]]
    assert np.corrcoef(a, b)[0, 1] > 0.3
