"""A phase-error table from the set itself: the projector's power-law gamma, read from its
second harmonic.

A projector whose output is its pattern value to the power γ shows the N-step decoder
``((1 + cos θ)/2)^γ`` instead of a sinusoid. Its harmonics, as fractions of the
fundamental, are fixed by γ alone (Liu, Wang, Lau, Hassebrook, "Gamma model and its
analysis for phase measuring profilometry", JOSA A 27(3) 553, 2010):

    B_h / B_1 = Π_{j=1}^{h−1} (γ − j) / Π_{j=2}^{h} (γ + j),   so   B_2 / B_1 = (γ − 1)/(γ + 2).

With N = 4 the set's noise fit (:mod:`app.recon.noise`) measures the 2nd harmonic as one
number per frequency common to all pixels (the Nyquist residual), while the 3rd and 5th
alias onto the fundamental, invisible in the set, as a phase error ≈ (B_5 − B_3)/B_1 ·
sin 4φ. Under the power law the first gives γ, and γ gives the error: a
:class:`~app.recon.gamma.PhaseErrorLUT` made from the set, applied where no learned table
is given.

What the real projector says (tests/recon/test_gamma_model.py, the CFPE captures: a home
projector, 8-bit camera, 4-step subsets of 12-step sets): the measured 2nd harmonic (its
B²-weighted mean share, :attr:`app.recon.noise.NoiseFit.mean_harmonics`: the fit's share
changes with the pixel's level) reads γ 1.42–1.56, and the table made from it reduces the
4-step phase error against the 12-step phase on all 36 scene × subset × period cases (scene
means 11–18 % of its RMS) and its systematic part by 35–83 %, but not all of it: the real
odd harmonics grow near the top of the camera's range, which no power law of the projector
holds (``benchmarks/bench_gamma_self.py``).

Only N = 4 is corrected: for N ≥ 8 the aliased harmonics are the 7th and above (4·10⁻⁴
of B at γ 1.5, under the noise); for N = 5 … 7 the 2nd harmonic shares its
residual column with others and is not isolated by the fit.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from app.recon.gamma import PhaseErrorLUT

F64 = npt.NDArray[np.float64]
#: samples of the fringe phase the table and the fit are synthesised from (a uniform grid sums
#: the harmonics that matter, below the 100th, exactly; the table interpolates between them:
#: ≤ 2·10⁻⁶ rad at γ 1.5)
SYNTH_SAMPLES = 1024
#: table entries per frequency: the linear interpolation between 512 bin centres follows the
#: error to ~4·10⁻⁶ rad at γ 1.5 (6.8·10⁻⁵ with 128), so that its Fourier series, which the
#: fused kernel evaluates, and the table give the same phase to ~10⁻⁵ rad
TABLE_BINS = 512
#: the only N whose aliased harmonics (3rd, 5th) are inferred from the measured 2nd
CORRECTED_STEPS = 4
#: a table whose RMS is below this (rad) is not applied: a sinusoidal projector's set reads
#: ≤ 3·10⁻⁵ rad (twin, γ 1.0), γ 1.1 reads 4·10⁻³; a correction of 10⁻³ rad, a tenth or less
#: of the phase noise of the sets here, changes RMS(e/σ) by < 0.5 %, while applying a table
#: costs the fused kernel ~2 ms CPU on a 1384 × 1032 set as its Fourier series (9 ms without;
#: 34 ms more as table look-ups: ``benchmarks/bench_gamma_kernel.py``)
MIN_TABLE_RMS_RAD = 1e-3
#: the γ range the set's 2nd harmonic is inverted over, and the grid's points
GAMMA_MIN, GAMMA_MAX, GAMMA_GRID = 0.1, 8.0, 160


def power_law_harmonic_ratio(gamma: float, h: int) -> float:
    """B_h / B_1 of the pattern ``((1 + cos θ)/2)^γ`` (dimensionless, signed).

    Args:
        gamma: the projector's exponent γ > 0.
        h: harmonic order, ≥ 1.
    """
    if h < 1:
        raise ValueError(f"h: need a harmonic order >= 1, got {h}")
    num = math.prod(gamma - j for j in range(1, h))
    den = math.prod(gamma + j for j in range(2, h + 1))
    return num / den


def measured_second_harmonic(gamma: float, steps: int = CORRECTED_STEPS) -> float:
    """The 2nd-harmonic coefficient the noise fit reads from a power-law projector's N-step set.

    Not quite (γ − 1)/(γ + 2): the fit's regressors are built from the decoded phasor, whose
    phase and magnitude carry the aliased 3rd and 5th harmonics (≈ 2.6 % more at γ 1.5). The
    fit is repeated here on the noiseless pattern over a uniform phase: the Nyquist residual
    ``Σ_n I_n (−1)^n / √N`` regressed on |z|·(cos 2φ, sin 2φ, cos 6φ, sin 6φ) of the decoded
    phasor z (:data:`app.recon.noise.SET_HARMONICS` = 2 harmonics, 2 and 6).

    Args:
        gamma: the exponent γ > 0.
        steps: N, even.

    Returns:
        The coefficient of |z| cos 2φ (dimensionless).
    """
    theta = (np.arange(SYNTH_SAMPLES) + 0.5) * (2.0 * np.pi / SYNTH_SAMPLES)
    delta = 2.0 * np.pi * np.arange(steps) / steps
    pattern = ((1.0 + np.cos(theta[None, :] + delta[:, None])) / 2.0) ** gamma  # (N, S)
    phasor = (pattern * np.exp(1j * delta)[:, None]).sum(axis=0)  # the fit's Σ I (cos, sin) δ
    nyquist = (pattern * np.cos(np.pi * np.arange(steps))[:, None]).sum(axis=0) / np.sqrt(steps)
    mag, unit = np.abs(phasor), phasor / np.abs(phasor)
    design = np.stack([f(mag * unit**h) for h in (2, 6) for f in (np.real, np.imag)], axis=1)
    return float(np.linalg.lstsq(design, nyquist, rcond=None)[0][0])


@lru_cache(maxsize=4)
def _measured_grid(steps: int) -> tuple[F64, F64]:
    """(γ, :func:`measured_second_harmonic`) on :data:`GAMMA_GRID` points, log-spaced over
    (:data:`GAMMA_MIN`, :data:`GAMMA_MAX`), γ ascending (made once: ~30 ms)."""
    gammas = np.geomspace(GAMMA_MIN, GAMMA_MAX, GAMMA_GRID)
    return gammas, np.array([measured_second_harmonic(float(g), steps) for g in gammas])


def gamma_from_measured_second_harmonic(ratio: float,
                                        steps: int = CORRECTED_STEPS) -> float | None:
    """γ whose :func:`measured_second_harmonic` is ``ratio``, or None where no γ in
    (:data:`GAMMA_MIN`, :data:`GAMMA_MAX`) gives it.

    Interpolated in a grid, then secant steps on the function itself.
    """
    gammas, measured = _measured_grid(steps)
    if not (math.isfinite(ratio) and measured[0] < ratio < measured[-1]):
        return None
    if not np.all(np.diff(measured) > 0):  # the inversion needs a monotone response
        raise RuntimeError("measured_second_harmonic is not monotone in γ on the grid")
    i = int(np.searchsorted(measured, ratio))
    g0, g1 = float(gammas[i - 1]), float(gammas[i])
    m0, m1 = float(measured[i - 1]), float(measured[i])
    for _ in range(3):  # secant steps from the grid's interpolation
        g = g0 + (ratio - m0) * (g1 - g0) / (m1 - m0)
        m = measured_second_harmonic(g, steps)
        if m == m1 or abs(m - ratio) < 1e-9:  # γ to ~1e-8: far below the fit's error
            return g
        g0, m0, g1, m1 = g1, m1, g, m
    return g1


def gamma_from_second_harmonic(ratio: float) -> float | None:
    """γ of a power-law projector whose 2nd harmonic is ``ratio`` = B_2/B_1.

    The inverse of ``(γ − 1)/(γ + 2)``: γ = (1 + 2r)/(1 − r). None where no γ > 0 gives
    ``ratio`` (r ≤ −1/2 or r ≥ 1: not a power law).
    """
    if not (math.isfinite(ratio) and -0.5 < ratio < 1.0):
        return None
    return (1.0 + 2.0 * ratio) / (1.0 - ratio)


def power_law_phase_error(gamma: float, steps: int, bins: int = TABLE_BINS) -> F64:
    """The N-step wrapped-phase error of a power-law projector, as a function of the phase.

    The pattern ``((1 + cos(θ + δ_n))/2)^γ``, δ_n = 2πn/N, is decoded as
    :func:`app.recon.phase.wrapped_phase` does (φ = arg Σ I_n e^{−iδ_n}) on
    :data:`SYNTH_SAMPLES` uniform θ, and the error e = φ − θ read at the bin centres of φ by
    linear interpolation in φ (φ(θ) rises monotonically for every γ in (:data:`GAMMA_MIN`,
    :data:`GAMMA_MAX`): dφ/dθ ≥ 0.06): the table :meth:`PhaseErrorLUT.apply` subtracts. The
    error is sampled, not averaged over bins: a bin mean of the few samples that fall in it
    (φ − θ binned as :meth:`PhaseErrorLUT.fit` does) put ~1·10⁻⁴ rad of sampling ripple into
    every entry, which no short series (:attr:`PhaseErrorLUT.series`) follows. Neither the
    pattern's offset nor the albedo changes it.

    Args:
        gamma: the exponent γ > 0.
        steps: N ≥ 3.
        bins: table entries.

    Returns:
        (bins,) float64, radians, at bin centres (i + 0.5)·2π/bins.
    """
    theta = (np.arange(SYNTH_SAMPLES) + 0.5) * (2.0 * np.pi / SYNTH_SAMPLES)
    delta = 2.0 * np.pi * np.arange(steps) / steps
    pattern = ((1.0 + np.cos(theta[None, :] + delta[:, None])) / 2.0) ** gamma  # (N, S)
    phasor = (pattern * np.exp(-1j * delta)[:, None]).sum(axis=0)
    measured = np.mod(np.angle(phasor), 2.0 * np.pi)
    error = np.angle(np.exp(1j * (measured - theta)))
    order = np.argsort(measured)
    centres = (np.arange(bins) + 0.5) * (2.0 * np.pi / bins)
    return np.asarray(np.interp(centres, measured[order], error[order], period=2.0 * np.pi),
                      np.float64)


def second_harmonic_ratios(harmonics: F64, sources: npt.NDArray[np.int64],
                           steps: int) -> F64 | None:
    """(K,) B_2/B_1 per frequency from the noise fit's set harmonics, or None where the fit
    does not isolate the 2nd harmonic (N ≠ :data:`CORRECTED_STEPS`).

    For N = 4 the one residual column is the Nyquist one, ``Σ_n I_n (−1)^n / 2``; a 2nd
    harmonic ``r·B cos(2(φ + δ_n))`` puts ``2rB cos 2φ`` there, and the fit's regressor is
    the phasor's magnitude ``2B`` times cos 2φ: its coefficient a_2 is r itself.

    Args:
        harmonics: (K, d, 2·S) float64, :attr:`app.recon.noise.NoiseFit.mean_harmonics`.
        sources: (d, S) int64, :attr:`app.recon.noise.NoiseFit.sources`.
        steps: N.
    """
    if steps != CORRECTED_STEPS or sources.shape[0] != 1 or int(sources[0, 0]) != 2:
        return None
    return np.asarray(harmonics[:, 0, 0], np.float64)


def _first_order_rms(ratio: float) -> float:
    """RMS of the N = 4 table to first order, |r_5 − r_3|/√2 (rad), at the closed form's γ of
    ``ratio``; inf where no γ fits (the full inversion decides)."""
    gamma = gamma_from_second_harmonic(ratio)
    if gamma is None:
        return math.inf
    rms = power_law_harmonic_ratio(gamma, 5) - power_law_harmonic_ratio(gamma, 3)
    return abs(rms) / math.sqrt(2.0)


def self_calibrated_table(harmonics: F64, sources: npt.NDArray[np.int64],
                          steps: int) -> PhaseErrorLUT | None:
    """The phase-error table a power-law projector with the set's 2nd harmonic gives.

    One γ per frequency (the projector's blur thins the harmonics of the finer fringes, so
    each frequency's own 2nd harmonic is the better guide to its 3rd and 5th).

    Args:
        harmonics, sources, steps: as :func:`second_harmonic_ratios`.

    Returns:
        :class:`PhaseErrorLUT` for N-step phase (``steps`` recorded, any fringe counts), or
        None where N ≠ 4, some frequency's 2nd harmonic fits no power law, or no row's RMS
        reaches :data:`MIN_TABLE_RMS_RAD` (a sinusoidal projector).
    """
    ratios = second_harmonic_ratios(harmonics, sources, steps)
    if ratios is None:
        return None
    if max(_first_order_rms(float(r)) for r in ratios) < 0.5 * MIN_TABLE_RMS_RAD:
        return None  # a sinusoidal projector: skip the inversion (~3 ms per set)
    gammas = [gamma_from_measured_second_harmonic(float(r)) for r in ratios]
    if any(g is None for g in gammas):
        return None
    table = np.stack([power_law_phase_error(float(g), steps) for g in gammas if g is not None])
    if float(np.sqrt(np.mean(table**2, axis=1)).max()) < MIN_TABLE_RMS_RAD:
        return None
    return PhaseErrorLUT(table, steps)
