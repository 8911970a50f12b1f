"""Phase-error lookup table against the closed-form error of a gamma-distorted 4-step set."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.recon.gamma import PhaseErrorLUT
from app.recon.phase import wrapped_phase

TWO_PI = 2 * math.pi


def _gamma_frames(phi, gamma=3.5, steps=4):
    delta = TWO_PI * np.arange(steps) / steps
    pattern = (0.5 + 0.5 * np.cos(phi[None] + delta[:, None, None])) ** gamma
    return np.rint(100 + 60000 * pattern).astype(np.uint16)


def test_lut_learned_on_one_phase_map_removes_the_gamma_error_of_another():
    rng = np.random.default_rng(0)
    train = rng.uniform(0, TWO_PI, (1, 200, 200))
    test = rng.uniform(0, TWO_PI, (1, 200, 200))
    w_train = wrapped_phase(_gamma_frames(train[0]), 4).phase
    w_test = wrapped_phase(_gamma_frames(test[0]), 4).phase
    before = np.angle(np.exp(1j * (w_test - test)))
    # N = 4 under gamma: the error is periodic in φ with period π/2 (harmonics 3 and 5 alias onto 1)
    assert 0.05 < np.sqrt(np.mean(before**2)) < 0.3
    spectrum = np.abs(
        np.fft.rfft(np.histogram(w_test[0].ravel(), 64, (0, TWO_PI), weights=before[0].ravel())[0])
    )
    assert np.argmax(spectrum[1:]) + 1 == 4
    lut = PhaseErrorLUT.fit(w_train, np.mod(train, TWO_PI), bins=256)
    after = np.angle(np.exp(1j * (lut.apply(w_test) - test)))
    assert np.sqrt(np.mean(after**2)) < 0.05 * np.sqrt(np.mean(before**2))
    assert lut.apply(w_test).min() >= 0 and lut.apply(w_test).max() < TWO_PI


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(wrapped=np.zeros((1, 4, 4)), reference=np.zeros((2, 4, 4))), "reference"),
        (dict(wrapped=np.zeros((1, 4, 4)), reference=np.zeros((1, 4, 4)), bins=4), "bins"),
        (
            dict(
                wrapped=np.zeros((1, 4, 4)),
                reference=np.zeros((1, 4, 4)),
                mask=np.ones((3, 3), bool),
            ),
            "mask",
        ),
    ],
)
def test_bad_input_names_argument(kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        PhaseErrorLUT.fit(**kwargs)


def test_learn_from_a_12_step_capture_corrects_its_4_step_subset():
    rng = np.random.default_rng(1)
    phi = rng.uniform(0, TWO_PI, (2, 160, 160))  # two frequencies, one scene each
    twelve = np.concatenate([_gamma_frames(p, steps=12) for p in phi])
    lut = PhaseErrorLUT.learn(twelve, 12, 4, frequencies=(4.0, 16.0), min_modulation=10.0)
    assert lut.steps == 4 and lut.frequencies == (4.0, 16.0) and lut.error_rad.shape == (2, 128)
    test = rng.uniform(0, TWO_PI, (160, 160))
    w4 = wrapped_phase(np.concatenate([_gamma_frames(test)] * 2), 4).phase
    before = np.angle(np.exp(1j * (w4 - test)))
    after = np.angle(np.exp(1j * (lut.apply(w4) - test)))
    assert np.sqrt(np.mean(after**2)) < 0.1 * np.sqrt(np.mean(before**2))
    assert np.allclose(lut.amplitude_rad(), np.sqrt(np.mean(lut.error_rad**2, axis=1)))


def test_table_round_trips_and_refuses_another_schedule():
    lut = PhaseErrorLUT(np.linspace(-0.01, 0.01, 2 * 16).reshape(2, 16), 4, (1920 / 48, 1920 / 45))
    back = PhaseErrorLUT.from_dict(lut.to_dict())
    assert back.steps == 4 and np.allclose(back.frequencies, lut.frequencies)
    assert np.allclose(back.error_rad, lut.error_rad, atol=1e-7)
    back.check_schedule(4, (1920 / 48, 1920 / 45))
    with pytest.raises(ValueError, match="^steps"):
        back.check_schedule(3, (1920 / 48, 1920 / 45))
    with pytest.raises(ValueError, match="^frequencies"):
        back.check_schedule(4, (1.0, 4.0))


@pytest.mark.parametrize(
    ("data", "name"),
    [
        ({"format": "other"}, "format"),
        ({"format": "fringescope-phase-error", "version": 9}, "version"),
        (
            {"format": "fringescope-phase-error", "version": 1, "error_rad": [[0.0] * 4]},
            "error_rad",
        ),
        ({"format": "fringescope-phase-error", "version": 1, "error_rad": "x"}, "error_rad"),
        (
            {
                "format": "fringescope-phase-error",
                "version": 1,
                "error_rad": [[0.0] * 8],
                "frequencies": [1, 2],
            },
            "frequencies",
        ),
    ],
)
def test_malformed_table_names_the_key(data, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        PhaseErrorLUT.from_dict(data)


@pytest.mark.parametrize(("kwargs", "name"), [
    (dict(reference_steps=12, steps=2), "steps"),
    (dict(reference_steps=10, steps=4), "reference_steps"),
    (dict(reference_steps=4, steps=4), "reference_steps"),
    (dict(reference_steps=12, steps=4, frequencies=(1.0, 2.0, 3.0)), "frequencies"),
])
def test_learn_bad_input_names_argument(kwargs, name):
    frames = np.concatenate([_gamma_frames(np.zeros((8, 8)), steps=12)] * 2)
    with pytest.raises(ValueError, match=f"^{name}"):
        PhaseErrorLUT.learn(frames, **kwargs)
