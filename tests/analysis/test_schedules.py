"""Predicted σ_φ and order-error rate of a schedule against Monte-Carlo on synthetic phases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.analysis.schedules import (
    order_error_probability,
    predict_schedule,
    step_sigmas_rad,
    wrapped_phase_sigma_rad,
)
from app.core.schedule import SCHEDULES, PatternSchedule
from app.recon.phase import wrapped_phase
from app.recon.unwrap import unwrap_phases

TWO_PI = 2.0 * math.pi


@pytest.mark.parametrize("steps", [3, 4, 6])
def test_wrapped_phase_sigma_matches_monte_carlo(steps):
    rng = np.random.default_rng(steps)
    a, b, sigma_i, n_px = 20000.0, 8000.0, 400.0, 40000
    phi = rng.uniform(0, TWO_PI, n_px)
    delta = TWO_PI * np.arange(steps) / steps
    frames = a + b * np.cos(phi[None] + delta[:, None]) + rng.normal(0, sigma_i, (steps, n_px))
    wp = wrapped_phase(np.rint(frames).astype(np.uint16)[:, None, :], steps)
    err = np.angle(np.exp(1j * (wp.phase[0, 0] - phi)))
    predicted = float(wrapped_phase_sigma_rad(sigma_i, b, steps))
    assert predicted == pytest.approx(math.sqrt(2.0 / steps) * sigma_i / b)
    assert np.std(err) == pytest.approx(predicted, rel=0.03)


def _monte_carlo_order_errors(
    schedule: PatternSchedule, sigma: float, n_px: int, seed: int
) -> float:
    """Fraction of pixels whose finest unwrapped phase is off by a fringe (no consistency
    rejection)."""
    rng = np.random.default_rng(seed)
    # projector coordinate / axis length, away from the absolute phase's wrap
    x = rng.uniform(0.1, 0.9, n_px)
    freqs = np.asarray(schedule.frequencies, np.float64)
    true = TWO_PI * freqs[:, None] * x[None]
    wrapped = np.mod(true + rng.normal(0, sigma, true.shape), TWO_PI)[:, None, :]
    unwrapped, _ = unwrap_phases(
        wrapped, schedule.frequencies, schedule.unwrap, consistency_rad=math.pi
    )
    return float(np.mean(np.abs(unwrapped[-1, 0] - true[-1]) > math.pi))


@pytest.mark.parametrize("schedule, sigma", [
    (PatternSchedule((1, 6, 36), 3), 0.17),
    (PatternSchedule((1, 4, 12, 36), 4), 0.28),
    (PatternSchedule((30, 35, 36), 3, unwrap="heterodyne"), 0.11),
])
def test_order_error_probability_matches_monte_carlo(schedule, sigma):
    n_px = 200_000
    p = float(order_error_probability(schedule, sigma))
    assert 2e-3 < p < 0.1  # a rate the sample resolves
    measured = _monte_carlo_order_errors(schedule, sigma, n_px, seed=7)
    # binomial 4σ + the Gaussian-tail approximation
    tol = 4.0 * math.sqrt(p * (1 - p) / n_px) + 0.1 * p
    assert measured == pytest.approx(p, abs=tol)


def test_hierarchical_step_sigma_is_the_textbook_form():
    s = PatternSchedule((1, 4, 12, 36), 4)
    sig = np.array([0.01, 0.02, 0.03, 0.04])
    got = step_sigmas_rad(s, sig)
    want = [math.hypot(4 * 0.01, 0.02), math.hypot(3 * 0.02, 0.03), math.hypot(3 * 0.03, 0.04)]
    assert got == pytest.approx(want)


def test_equal_ratios_minimise_the_worst_step():
    """The rule behind the 9-frame schedule: for 1 → k → 36 the largest step σ is least at k = 6."""
    worst = {
        k: float(step_sigmas_rad(PatternSchedule((1, k, 36), 3), 0.05).max())
        for k in (2, 3, 4, 6, 9, 12, 18)
    }
    assert min(worst, key=worst.get) == 6


def test_predict_schedule_figures():
    s = SCHEDULES["geometric-9"]
    b = np.array([50.0, 100.0, np.nan])
    pred = predict_schedule(s, 1.0, b, 0.05)
    sig = math.sqrt(2 / 3) / np.array([50.0, 100.0])
    assert pred.sigma_phi_rad == pytest.approx(np.median(sig))
    assert pred.sigma_mm == pytest.approx(0.05 * np.median(sig))
    assert 0.0 <= pred.order_error_rate < 1e-12
    with pytest.raises(ValueError, match="modulation"):
        predict_schedule(s, 1.0, np.array([np.nan]), 0.05)


def test_bad_arguments_name_themselves():
    with pytest.raises(ValueError, match="steps"):
        wrapped_phase_sigma_rad(1.0, 10.0, 2)
    with pytest.raises(ValueError, match="sigma_i"):
        wrapped_phase_sigma_rad(-1.0, 10.0, 3)
    with pytest.raises(ValueError, match="schedule"):
        step_sigmas_rad("paper-16", 0.1)  # type: ignore[arg-type]
