"""The noise-aware modulation rule (app.recon.validity) against Monte-Carlo, and its wiring."""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest

from app.core.reasons import Reason
from app.core.schedule import PatternSchedule
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor, compute_phase
from app.recon.model import evaluate_height_slope
from app.recon.phase import MODULATION_FLOOR_DN, wrapped_phase
from app.recon.reconstructor import SensorNoise
from app.recon.unwrap import unwrap_phases
from app.recon.validity import (
    max_depth_sigma_mm,
    min_phasor_snr,
    modulation_threshold,
    phasor_phase_density,
    phasor_tail_factor_sq,
    step_gains,
    undetected_order_error_rate,
)

TWO_PI = 2 * math.pi


def test_phase_density_is_the_noisy_phasors():
    rng = np.random.default_rng(1)
    snr = 2.5
    z = snr + rng.normal(size=400_000) + 1j * rng.normal(size=400_000)
    hist, edges = np.histogram(np.angle(z), bins=64, range=(-math.pi, math.pi), density=True)
    centres = 0.5 * (edges[1:] + edges[:-1])
    assert np.allclose(hist, phasor_phase_density(centres, snr), atol=0.01, rtol=0.03)
    grid = np.linspace(-math.pi, math.pi, 20001)
    assert np.trapezoid(phasor_phase_density(grid, 0.7), grid) == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(phasor_phase_density(grid, 0.0), 1 / TWO_PI)  # no signal: uniform


def test_step_gains_of_both_chains():
    assert step_gains((1, 4, 12, 36)).tolist() == [[4, -1, 0, 0], [0, 3, -1, 0], [0, 0, 3, -1]]
    # heterodyne 30, 35, 36: 36 − 35 = 1 (absolute), 35 − 30 = 5, then 36
    assert np.allclose(step_gains((30, 35, 36), "heterodyne"), [[1, -6, 5], [-7.2, 7.2, -1]])


def _monte_carlo(
    schedule: PatternSchedule, snr: float, n_px: int, seed: int
) -> tuple[float, float]:
    """(undetected order-error rate, inconsistent rate) of ``schedule``'s real decoder (N-step
    phase, then :func:`unwrap_phases`) on uint16 pixels at phasor SNR ``snr`` in every
    frequency."""
    rng = np.random.default_rng(seed)
    n = schedule.steps
    sigma_i = 40.0  # codes: quantisation is negligible
    b = snr * sigma_i / math.sqrt(n / 2)
    x = rng.uniform(0.05, 0.95, n_px)  # projector position, fraction of the width
    frames = np.empty((schedule.n_frames, 1, n_px), np.uint16)
    for fi, k in enumerate(schedule.frequencies):
        for s in range(n):
            img = 30000 + b * np.cos(TWO_PI * k * x + TWO_PI * s / n) + rng.normal(0, sigma_i, n_px)
            frames[fi * n + s, 0] = np.rint(img).astype(np.uint16)
    wp = wrapped_phase(frames, n)
    phi, consistent = unwrap_phases(wp.phase, schedule.frequencies, schedule.unwrap)
    wrong = np.abs(phi[-1, 0] - TWO_PI * schedule.frequencies[-1] * x) > math.pi
    return float((wrong & consistent[0]).mean()), float((~consistent[0]).mean())


def test_rate_is_the_phase_domain_monte_carlo():
    """The convolution of the exact phase densities against sampled phasors, step by step."""
    rng = np.random.default_rng(5)
    freqs = (1, 6, 36)
    snr = 4.5
    theta = [
        np.angle(snr + rng.normal(size=2_000_000) + 1j * rng.normal(size=2_000_000)) for _ in freqs
    ]
    got = 0.0
    for g in step_gains(freqs):
        d = sum(gk * t for gk, t in zip(g, theta, strict=True))
        m = np.round(d / TWO_PI)
        got += float(((m != 0) & (np.abs(d - TWO_PI * m) < math.pi / 2)).mean())
    assert undetected_order_error_rate(freqs, snr=snr) == pytest.approx(got, rel=0.05)


@pytest.mark.parametrize(
    "schedule",
    [
        PatternSchedule((1, 6), 4),
        PatternSchedule((1, 4, 12, 36), 4),
        PatternSchedule((1, 6, 36), 3),
    ],
    ids=["one-step", "paper-16", "geometric-9"],
)
def test_order_error_rate_at_the_threshold_is_the_bound_hierarchical(schedule):
    rate = 3e-3  # large enough to count: ~1200 events in 4e5 pixels (±3 %)
    snr = min_phasor_snr(schedule.frequencies, schedule.unwrap, rate=rate)
    assert undetected_order_error_rate(schedule.frequencies, snr=snr) == pytest.approx(
        rate, rel=1e-3
    )
    got, inconsistent = _monte_carlo(schedule, snr, 400_000, seed=2)
    # the sum over the steps is an upper bound: an error of one step passes unnoticed only if the
    # other steps pass the test too (at this high rate 30-40 % of pixels fail it; at 1e-6, ~none)
    assert rate * (1.0 - inconsistent) * 0.9 <= got <= 1.1 * rate, (got, inconsistent)
    if len(schedule.frequencies) == 2:
        assert got == pytest.approx(rate, rel=0.1)
    # and the rule is not a loose bound: at a 20 % lower SNR the rate is well above it
    low, _ = _monte_carlo(schedule, 0.8 * snr, 400_000, seed=3)
    assert low > 2 * rate


def test_order_error_rate_at_the_threshold_is_bounded_heterodyne():
    schedule = PatternSchedule((30, 35, 36), 3, unwrap="heterodyne")
    rate = 3e-3
    snr = min_phasor_snr(schedule.frequencies, schedule.unwrap, rate=rate)
    got, _ = _monte_carlo(schedule, snr, 400_000, seed=4)
    # a later, non-integer step can still catch an earlier error: the bound is an upper bound
    assert 0.0 < got <= 1.1 * rate, got


def test_threshold_follows_the_noise_and_has_a_floor():
    snr = min_phasor_snr((1, 4, 12, 36))
    t = modulation_threshold(
        np.array([0.0, 100.0, 10_000.0]), 4, snr, read_var_dn2=4.0, gain_dn_per_e=0.5
    )
    expected = snr * np.sqrt(0.5 * (4.0 + 0.5 * np.array([0.0, 100.0, 10_000.0])))
    assert np.allclose(t, np.maximum(MODULATION_FLOOR_DN, expected))
    quiet = modulation_threshold(np.array([10.0]), 4, snr, read_var_dn2=0.0, gain_dn_per_e=0.0)
    assert quiet[0] == MODULATION_FLOOR_DN
    # a stricter bound or a longer chain needs more SNR
    assert min_phasor_snr((1, 4, 12, 36), rate=1e-9) > snr
    assert min_phasor_snr((30, 35, 36), "heterodyne") > snr
    with pytest.raises(ValueError, match="^rate"):
        min_phasor_snr((1, 4, 12, 36), rate=0.0)
    with pytest.raises(ValueError, match="^order_error_rate"):
        Reconstructor(Rig().calibration(), order_error_rate=1.0)


@pytest.fixture(scope="module")
def dim_rig():
    return Rig()


def _dim_frames(rig: Rig, seed: int = 0) -> np.ndarray:
    """8-bit frames whose modulation falls from 12 to 0.5 codes across the image (A = B + 2)."""
    amp = np.linspace(12.0, 0.5, rig.width)[None, :] * np.ones((rig.height, 1))
    return rig.render(bump_surface(rig), background=amp + 2.0, amplitude=amp, noise=0.5,
                      rng=np.random.default_rng(seed))


def test_rule_in_both_paths_and_explicit_threshold_wins(dim_rig):
    frames = _dim_frames(dim_rig)
    noise = SensorNoise.typical(255)
    # the modulation part alone
    rec = Reconstructor(dim_rig.calibration(), noise=noise, gross_error_mm=None)
    a = rec.run(frames, fast=False)
    a_reason, a_mod = a.reason.copy(), a.modulation.copy()
    b = rec.run(frames, fast=True)
    # the rule itself agrees exactly; float32 against float64 may flip a pixel whose unwrapping
    # residual sits on the π/2 consistency test (integer lattice points of very dim pixels)
    assert np.array_equal(a_reason == Reason.LOW_MODULATION, b.reason == Reason.LOW_MODULATION)
    differ = a_reason != b.reason
    assert differ.sum() <= 10 and set(a_reason[differ].tolist()) | set(
        b.reason[differ].tolist()
    ) <= {0, 3, 7}
    # the oracle's LOW_MODULATION is exactly the rule on its own B (all frequencies) and A
    wp = wrapped_phase(frames, 4)
    thr = modulation_threshold(
        wp.background,
        4,
        min_phasor_snr((1, 4, 12, 36)),
        noise.read_noise_dn**2,
        noise.gain_dn_per_e,
    )
    low = wp.modulation.min(axis=0) < thr
    assert np.array_equal(a_reason == Reason.LOW_MODULATION, low)
    # dim pixels pass: B of 3 codes is far below the former 2 % of full scale (5.1)
    dim = (a_mod > 3.0) & (a_mod < 5.0)
    assert dim.sum() > 500 and (a_reason[dim] == Reason.OK).mean() > 0.95
    # and are right: no order errors among the valid pixels
    truth = dim_rig.finest_phase(bump_surface(dim_rig))
    rec_p = Reconstructor(dim_rig.calibration(), noise=noise, with_phase=True, gross_error_mm=None)
    p = rec_p.run(frames, fast=True)
    assert np.nanmax(np.abs(p.phase - truth)) < 1.0
    # an explicit threshold replaces the rule, in both paths
    for fast in (False, True):
        r = Reconstructor(dim_rig.calibration(), min_modulation=5.1).run(frames, fast=fast)
        assert (r.reason[wp.modulation.min(axis=0) < 5.0] == Reason.LOW_MODULATION).all()
        r = Reconstructor(dim_rig.calibration(), min_modulation=0.0).run(frames, fast=fast)
        assert (r.reason != Reason.LOW_MODULATION).all()


def test_compute_phase_uses_the_rule_and_its_noise(dim_rig):
    frames = _dim_frames(dim_rig, seed=1)
    quiet = compute_phase(frames, dim_rig.schedule)  # SensorNoise.typical(255)
    loud = compute_phase(frames, dim_rig.schedule, noise=SensorNoise(0.0, 3.0))
    n_quiet = (quiet.reason == Reason.LOW_MODULATION).sum()
    n_loud = (loud.reason == Reason.LOW_MODULATION).sum()
    assert n_loud > n_quiet  # a noisier camera needs more modulation
    explicit = compute_phase(
        frames, dim_rig.schedule, min_modulation=1.0, noise=SensorNoise(0.0, 3.0)
    )
    assert (explicit.reason == Reason.LOW_MODULATION).sum() < n_quiet
    with pytest.raises(ValueError, match="^noise"):
        compute_phase(frames, dim_rig.schedule, noise=3.0)  # type: ignore[arg-type]


def test_depth_sigma_part_of_the_rule(dim_rig):
    limit = max_depth_sigma_mm(0.5, 1e-6)
    assert math.erfc(0.5 / (limit * math.sqrt(2))) == pytest.approx(1e-6, rel=1e-6)
    assert limit == pytest.approx(0.1022, abs=1e-4)
    frames = _dim_frames(dim_rig, seed=2)
    free_rec = Reconstructor(dim_rig.calibration(), gross_error_mm=None, with_phase=True)
    free = free_rec.run(frames, fast=False)
    free_reason, free_sigma = free.reason.copy(), free.sigma.copy()
    # the noise part weighed by the phasor tail at θ_g = 0.5 mm / |∂z/∂φ| (validity, step 5)
    _, _, slope = evaluate_height_slope(free_rec._tables64[0], free.phase.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        tail = phasor_tail_factor_sq(np.nan_to_num(0.25 / slope**2, nan=np.inf))
    weighed = np.sqrt(free.sigma_noise.astype(np.float64) ** 2 * tail
                      + free.sigma_model.astype(np.float64) ** 2)
    for fast in (False, True):
        res = Reconstructor(dim_rig.calibration()).run(frames, fast=fast)
        ok = free_reason == Reason.OK
        assert ok.sum() > 1000
        noisy = ok & (weighed > limit * 1.001)
        quiet = ok & (weighed < limit * 0.999)
        assert noisy.sum() > 100 and quiet.sum() > 100
        assert (res.reason[noisy] == Reason.UNCERTAIN).all() and (
            res.reason[quiet] == Reason.OK
        ).all()
        # the tail refuses pixels the Gaussian reading of σ would have passed
        assert (res.reason[ok & (free_sigma < limit * 0.999)] == Reason.UNCERTAIN).any()
    # an explicit max_sigma_mm or min_modulation replaces it
    res = Reconstructor(dim_rig.calibration(), max_sigma_mm=10.0).run(frames)
    assert not (res.reason == Reason.UNCERTAIN).any()
    res = Reconstructor(dim_rig.calibration(), min_modulation=1.0).run(frames)
    assert not (res.reason == Reason.UNCERTAIN).any()


def test_the_phasor_tail_factor_is_theta_over_sin_theta_squared():
    t = np.linspace(0.0, (math.pi / 2) ** 2, 5001)
    exact = np.ones_like(t)
    exact[1:] = t[1:] / np.sin(np.sqrt(t[1:])) ** 2
    np.testing.assert_allclose(phasor_tail_factor_sq(t), exact, rtol=1.1e-4)
    assert phasor_tail_factor_sq(0.0) == 1.0
    cap = (math.pi / 2) ** 2  # θ_g capped at π/2: (π/2 / 1)²
    np.testing.assert_allclose(phasor_tail_factor_sq([10.0, np.inf]), cap, rtol=1.1e-4)
    with pytest.raises(ValueError, match="^theta_sq"):
        phasor_tail_factor_sq(-1.0)


@pytest.mark.parametrize(("snr", "theta_g"), [(5.0, 1.0), (4.0, 0.8), (8.0, 0.6), (3.0, 1.4)])
def test_a_phasors_phase_error_beyond_theta_g_is_bounded_by_the_tail_not_the_gaussian(snr, theta_g):
    """P(|θ| > θ_g) from the exact density of a phasor's phase (Goodman): above the Gaussian's
    2·Q(a·θ_g) that the Gaussian reading of σ = 1/a assumes, below the half-planes' bound
    2·Q(a·sin θ_g) the rule uses — which the factor θ_g / sin θ_g turns into a σ."""
    th = np.linspace(theta_g, math.pi, 200001)
    tail = 2.0 * float(np.trapezoid(phasor_phase_density(th, snr), th))
    q = NormalDist().cdf
    gaussian = 2.0 * (1.0 - q(snr * theta_g))
    half_planes = 2.0 * (1.0 - q(snr * math.sin(theta_g)))
    assert 2.0 * gaussian < tail <= half_planes * 1.0001
    # the weighed σ = θ_g/(a·sin θ_g) gives the half-planes' probability as a Gaussian's
    weighed_sigma = math.sqrt(float(phasor_tail_factor_sq(theta_g**2))) / snr
    assert 2.0 * (1.0 - q(theta_g / weighed_sigma)) == pytest.approx(half_planes, rel=2e-3)
