"""A phase-error table as a short Fourier series of the phase (what the fused kernel evaluates):
it reproduces a smooth table (the power law's, one learned from a clean phase map) to its
tolerance, is refused for a noisy or sharp one, and the kernel's float32 evaluation from the
phasor equals the float64 series."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from numba import njit

from app.recon import fast
from app.recon.gamma import SERIES_MAX_DEV_RAD, PhaseErrorLUT, fit_series
from app.recon.gamma_model import power_law_phase_error
from app.recon.phase import wrapped_phase

TWO_PI = 2 * math.pi


def _table_error(lut: PhaseErrorLUT, phases: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(K, M) the error ``lut.apply`` subtracts at ``phases`` (M,), rad."""
    w = np.broadcast_to(phases, (lut.error_rad.shape[0], phases.size))[:, None, :]
    return np.asarray(np.angle(np.exp(1j * (w - lut.apply(w))))[:, 0], np.float64)


def _probe_phases(seed: int) -> npt.NDArray[np.float64]:
    """100 000 random phases and the circle's edges, rad in [0, 2π)."""
    rng = np.random.default_rng(seed)
    edge = np.array([0.0, 1e-9, math.pi / 4, math.pi, TWO_PI - 1e-9])
    return np.concatenate([rng.uniform(0.0, TWO_PI, 100_000), edge])


@pytest.mark.parametrize("gamma", [1.1, 1.33, 1.5, 2.2])
def test_the_series_reproduces_the_power_law_table(gamma):
    lut = PhaseErrorLUT(np.stack([power_law_phase_error(gamma, 4)] * 2), 4)
    series = lut.series
    assert series is not None and series.period == 4 and series.harmonics == 3
    w = _probe_phases(1)
    dev = np.abs(series.error_at(np.stack([w, w])) - _table_error(lut, w)).max()
    assert dev <= SERIES_MAX_DEV_RAD
    assert dev <= series.max_dev_rad + 1e-7  # the fitting grid found the largest deviation
    # the table's size, not a flat series that passes by being small
    assert np.abs(lut.error_rad).max() > 40 * SERIES_MAX_DEV_RAD


def _gamma_frames(phi: npt.NDArray[np.float64], gamma: float) -> npt.NDArray[np.uint16]:
    delta = TWO_PI * np.arange(4) / 4
    pattern = (0.5 + 0.5 * np.cos(phi[None] + delta[:, None, None])) ** gamma
    return np.rint(100 + 60000 * pattern).astype(np.uint16)


def test_the_series_reproduces_a_table_learned_from_a_clean_phase_map():
    """``PhaseErrorLUT.fit`` on 160 000 noiseless pixels of a γ 1.5 projector: bin means smooth
    enough for a 3-harmonic series."""
    truth = np.random.default_rng(0).uniform(0.0, TWO_PI, (1, 400, 400))
    wrapped = wrapped_phase(_gamma_frames(truth[0], 1.5), 4).phase
    learned = PhaseErrorLUT.fit(wrapped, truth, bins=128)
    lut = PhaseErrorLUT(learned.error_rad, 4, (1.0,))
    series = lut.series
    assert series is not None
    w = _probe_phases(2)
    assert np.abs(series.error_at(w[None]) - _table_error(lut, w)).max() <= SERIES_MAX_DEV_RAD


def test_a_noisy_or_sharp_table_gets_no_series():
    rng = np.random.default_rng(3)
    smooth = power_law_phase_error(1.5, 4)
    noisy = PhaseErrorLUT(smooth[None] + rng.normal(0.0, 3e-4, (1, smooth.size)), 4)
    assert noisy.series is None  # bins' own noise: no short series follows it
    assert PhaseErrorLUT(power_law_phase_error(3.0, 4)[None], 4).series is None  # sharp
    assert PhaseErrorLUT(smooth[None], 0).series is None  # the period is not recorded
    # 3 harmonics of 4φ reach the Nyquist harmonic of a 24-bin table: no series
    assert fit_series(np.zeros((1, 24)), 4) is None
    assert fit_series(np.zeros((1, 26)), 4) is not None


@njit(cache=False)
def _kernel_series(y: npt.NDArray[np.float32], x: npt.NDArray[np.float32],
                   coefs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:  # pragma: no cover
    c = fast._series_row(coefs, 0)
    out = np.empty_like(y)
    for i in range(y.shape[0]):
        q = x[i] * x[i] + y[i] * y[i]
        out[i] = fast._series_correct(fast.atan2_0_2pi(y[i], x[i]), y[i], x[i], q, c)
    return out


def test_the_kernel_evaluates_the_series_from_the_phasor():
    """float32 from (x, y), no atan2 in the series: the float64 series at atan2(y, x) to
    float32 precision, wrapped to [0, 2π) as the table's look-up is."""
    lut = PhaseErrorLUT(power_law_phase_error(1.5, 4)[None], 4)
    series = lut.series
    assert series is not None
    rng = np.random.default_rng(5)
    phi = np.concatenate([rng.uniform(0.0, TWO_PI, 100_000), [0.0, 1e-7, TWO_PI - 1e-6]])
    mag = rng.uniform(0.5, 3000.0, phi.size)  # codes: modulations from faint to bright
    y = (mag * np.sin(phi)).astype(np.float32)
    x = (mag * np.cos(phi)).astype(np.float32)
    got = _kernel_series(y, x, series.kernel_coefficients()).astype(np.float64)
    w = np.mod(np.arctan2(y.astype(np.float64), x.astype(np.float64)), TWO_PI)
    want = w - series.error_at(w[None])[0]
    assert np.abs(np.angle(np.exp(1j * (got - want)))).max() < 2e-6
    assert got.min() >= 0.0 and got.max() < TWO_PI
    # no fringe (x = y = 0): the constant term only, finite
    zero = np.zeros(1, np.float32)
    assert np.isfinite(_kernel_series(zero, zero, series.kernel_coefficients())).all()
