"""The batch job's table figures: the same numbers as numpy's, by a cheaper path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.batch.setjob import median_float32


def _cases() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    sigma = rng.gamma(3.0, 0.05, 1384 * 1032).astype(np.float32)
    return {
        "camera-sized, even": sigma,
        "odd": sigma[:100_001].copy(),
        "one": np.array([0.25], np.float32),
        "two": np.array([0.1, 0.2], np.float32),  # the float32 mean of the middle pair
        "zeros and inf": np.array([0.0, np.inf, 3.0, 0.0, np.inf], np.float32),
        "ties": np.full(10, 0.125, np.float32),
        "negative values": rng.normal(0.0, 1.0, 1001).astype(np.float32),
        "negative zero": np.array([-0.0, 1.0, 2.0], np.float32),
    }


@pytest.mark.parametrize("name", list(_cases()))
def test_median_float32_is_numpys_median(name):
    values = _cases()[name]
    expected = float(np.median(values))
    got = median_float32(values.copy())
    assert got == expected, (got, expected)


def test_median_float32_nan_and_empty():
    assert math.isnan(median_float32(np.array([1.0, np.nan, 2.0], np.float32)))
    assert math.isnan(median_float32(np.array([1.0, -np.nan, 2.0], np.float32)))
    assert math.isnan(median_float32(np.empty(0, np.float32)))


def test_median_float32_names_its_argument():
    with pytest.raises(ValueError, match="^values"):
        median_float32(np.zeros(3))


def test_a_gamma_projectors_set_says_which_table_corrected_it():
    """``reconstruct``/``reprocess`` pass the set's own table to the run: the result (and the CLI
    line) says ``set``, not ``given``; a learned table wins and says ``learned``."""
    from app.batch.setjob import ReconOptions, noise_summary, reconstruct_captures
    from app.devices.sim.ideal import ideal_calibration
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.optics import rig_by_name
    from app.devices.sim.world import SimulatedWorld
    from app.recon.gamma import PhaseErrorLUT

    rig = rig_by_name("default", distortion=False)
    cal = ideal_calibration(rig)
    world = SimulatedWorld("intestine_flap", seed=2, projector_gamma=1.5, rig=rig)
    capture = render_capture_set("intestine_flap", exposure_ms=15.0, world=world)[0]

    own = reconstruct_captures([capture], cal, ReconOptions()).result
    assert own.phase_error_source == "set"
    assert noise_summary(own).endswith(", phase_error=set")
    learned = PhaseErrorLUT(np.zeros((4, 64)), steps=4,
                            frequencies=tuple(float(k) for k in cal.pattern.frequencies))
    taught = reconstruct_captures([capture], cal, ReconOptions(phase_error=learned)).result
    assert taught.phase_error_source == "learned"
    assert noise_summary(taught).endswith(", phase_error=learned")
