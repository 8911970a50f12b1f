"""The camera's noise measured from live sets (app.service.sensor_noise)."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.schedule import PatternSchedule
from app.recon.reconstructor import SensorNoise
from app.service.sensor_noise import LiveNoise

SCHEDULE = PatternSchedule()  # 4 frequencies x 4 steps


def _fringe_set(noise: SensorNoise, rng: np.random.Generator, *, moving_dn: float = 0.0,
                shape: tuple[int, int] = (96, 128)) -> np.ndarray:
    """A 16-frame set of a scene with a range of intensities, with ``noise`` (and, if given, a
    background drift of ``moving_dn`` between the frames of each group: motion)."""
    h, w = shape
    a = np.linspace(20.0, 200.0, w)[None, :].repeat(h, 0)
    b = 0.4 * a
    u = np.arange(w)[None, :] * np.ones((h, 1))
    frames = []
    for k in SCHEDULE.frequencies:
        for n in range(SCHEDULE.steps):
            mean = (
                a
                + n * moving_dn
                + b * np.cos(2 * np.pi * k * u / w + 2 * np.pi * n / SCHEDULE.steps)
            )
            frames.append(
                mean + rng.normal(0.0, 1.0, mean.shape) * np.sqrt(noise.variance_dn2(mean))
            )
    return np.clip(np.rint(frames), 0, 255).astype(np.uint8)


def test_the_estimate_is_the_cameras_and_motion_never_makes_it_quieter():
    rng = np.random.default_rng(0)
    # noisier than SensorNoise.typical(255)
    camera = SensorNoise(gain_dn_per_e=0.03, read_noise_dn=1.2)
    live = LiveNoise(interval_s=10.0)
    assert live.current is None and live.describe()["source"] == "nominal"
    assert live.due(0.0, SCHEDULE) and not live.due(
        0.0, PatternSchedule(frequencies=(1, 6, 36), steps=3)
    )
    moving = live.update(_fringe_set(camera, rng, moving_dn=3.0), SCHEDULE, 255, now_s=0.0)
    assert moving is not None and not live.due(5.0, SCHEDULE) and live.due(10.0, SCHEDULE)
    still = live.update(_fringe_set(camera, rng), SCHEDULE, 255, now_s=10.0)
    assert still is not None and still.variance_dn2(64.0) < moving.variance_dn2(64.0)
    for mean in (30.0, 100.0, 180.0):  # the camera's own noise, not the guess
        assert np.sqrt(still.variance_dn2(mean)) == pytest.approx(
            np.sqrt(camera.variance_dn2(mean)), rel=0.1
        )
    assert live.update(_fringe_set(camera, rng, moving_dn=3.0), SCHEDULE, 255, now_s=20.0) is still
    d = live.describe()
    assert (
        d["source"] == "measured"
        and d["estimates"] == 3
        and d["read_noise_dn"] == pytest.approx(1.2, rel=0.2)
    )


def test_measuring_off_and_bad_interval():
    live = LiveNoise(interval_s=0.0)
    assert not live.due(1e9, SCHEDULE) and live.describe()["source"] == "nominal (measuring off)"
    with pytest.raises(ValueError, match="interval_s"):
        LiveNoise(interval_s=-1.0)


def test_a_4_step_estimate_keeps_the_projectors_gamma_table_for_its_schedule():
    """The live estimate also reads the projector's gamma from the set's 2nd harmonic: a power
    law of γ 1.5 gives the table of the aliased 3rd and 5th harmonics, kept for that schedule
    only (another schedule's sets get none until measured)."""
    from app.recon.gamma_model import power_law_phase_error

    rng = np.random.default_rng(2)
    h, w = 96, 128
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    frames = []
    for k in SCHEDULE.frequencies:
        for n in range(SCHEDULE.steps):
            theta = 2 * np.pi * k * (x + 0.37 * y) / w + 2 * np.pi * n / SCHEDULE.steps
            mean = 10.0 + 200.0 * (0.4 + 0.6 * y / h) * ((1 + np.cos(theta)) / 2) ** 1.5
            frames.append(mean + rng.normal(0.0, 0.7, mean.shape))
    stack = np.clip(np.rint(frames), 0, 255).astype(np.uint8)
    live = LiveNoise(interval_s=1.0)
    assert live.phase_error(SCHEDULE) is None
    live.update(stack, SCHEDULE, 255, now_s=0.0)
    table = live.phase_error(SCHEDULE)
    assert table is not None and table.error_rad.shape[0] == len(SCHEDULE.frequencies)
    truth = power_law_phase_error(1.5, 4)
    for row in table.error_rad:  # within 10 % of the true table's RMS
        assert np.sqrt(np.mean((row - truth) ** 2)) < 0.1 * np.sqrt(np.mean(truth**2))
    # the status says how large the correction the live sets measured is
    rms = float(np.sqrt(np.mean(table.error_rad**2)))
    assert live.describe()["gamma_table_rms_rad"] == pytest.approx(rms, abs=1e-6) and rms > 1e-3
    assert live.phase_error(PatternSchedule(frequencies=(1, 4, 12, 36), steps=4,
                                            width=912)) is None
