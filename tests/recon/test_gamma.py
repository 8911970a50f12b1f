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
    spectrum = np.abs(np.fft.rfft(np.histogram(w_test[0].ravel(), 64, (0, TWO_PI), weights=before[0].ravel())[0]))
    assert np.argmax(spectrum[1:]) + 1 == 4
    lut = PhaseErrorLUT.fit(w_train, np.mod(train, TWO_PI), bins=256)
    after = np.angle(np.exp(1j * (lut.apply(w_test) - test)))
    assert np.sqrt(np.mean(after**2)) < 0.05 * np.sqrt(np.mean(before**2))
    assert lut.apply(w_test).min() >= 0 and lut.apply(w_test).max() < TWO_PI


@pytest.mark.parametrize(("kwargs", "name"), [
    (dict(wrapped=np.zeros((1, 4, 4)), reference=np.zeros((2, 4, 4))), "reference"),
    (dict(wrapped=np.zeros((1, 4, 4)), reference=np.zeros((1, 4, 4)), bins=4), "bins"),
    (dict(wrapped=np.zeros((1, 4, 4)), reference=np.zeros((1, 4, 4)), mask=np.ones((3, 3), bool)), "mask"),
])
def test_bad_input_names_argument(kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        PhaseErrorLUT.fit(**kwargs)
