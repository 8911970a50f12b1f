"""Noise-aware modulation threshold: a pixel is decoded when its fringe orders can be trusted.

A fixed modulation threshold (say 2 % of full scale) ignores that dim pixels are also quiet:
the phase noise depends on B/σ_I, not on B. The rule here follows the unwrapping chain.

1. **Wrapped phase.** The N-step sums ``X = Σ I_n cos δ_n``, ``Y = −Σ I_n sin δ_n`` are a
   phasor of length ``√m2 = N·B/2`` plus circular Gaussian noise of variance
   ``σ_I²·N/2`` per component (Σ cos²δ = Σ sin²δ = N/2, Σ cos δ sin δ = 0 for N ≥ 3). With
   the phasor SNR ``a = √m2 / (σ_I·√(N/2)) = B·√(N/2)/σ_I``, the phase error θ has the
   exact density (a Gaussian phasor's phase, e.g. Goodman, *Statistical Optics*, Sec. 2.9)

       p(θ) = e^{−a²/2}/(2π) + a·cos θ·e^{−a² sin²θ/2}·Φ(a cos θ)/√(2π),

   whose tails are heavier than the small-noise Gaussian of σ = 1/a.
2. **Unwrapping step s** (:func:`app.recon.unwrap.unwrap_chain`: step phases are integer
   combinations ``c_s · φ_w`` of the wrapped phases, of ``f_s`` fringes): with every
   earlier order right the rounding argument's error is ``d_s = g_s · θ``,
   ``g_s = (f_s/f_{s−1})·c_{s−1} − c_s`` (hierarchical: ``g = (r, −1)``, r the ratio). The
   errors of different frequencies are independent (other frames), so the density of d_s
   is the convolution of the scaled densities of step 1.
3. **Undetected order error.** The chain rounds ``d_s`` to the nearest multiple of 2π and
   rejects the pixel (UNWRAP_INCONSISTENT) when the remainder is ≥ the consistency
   threshold c (π/2 by default). An order error passes unnoticed only when
   ``d_s ∈ (2πm − c, 2πm + c)`` for some m ≠ 0 (for c = π/2: |d_s| > 3π/2), probability
   ``P_s(a)``. The rule bounds the sum over the steps (a union bound over the chain):

       Σ_s P_s(a) ≤ rate   (default :data:`DEFAULT_ORDER_ERROR_RATE` = 1e-6 per pixel)

   and :func:`min_phasor_snr` solves it for the least SNR ``a_min`` (bisection; P_s falls
   with a). Every frequency is taken at the pixel's weakest modulation (``m2min``), which
   bounds the rate from above.
4. **The threshold** per pixel, with σ_I² from the camera's noise model at the pixel's mean
   intensity A (shot + read: ``read² + gain·A``, :class:`~app.recon.reconstructor.SensorNoise`):

       m2min ≥ max(m2_floor, a_min²·(N/2)·σ_I²(A))   ⇔   B_min ≥ max(B_floor, a_min·√(2/N)·σ_I(A)).

   ``B_floor`` (:data:`~app.recon.phase.MODULATION_FLOOR_DN`, 2 DN less a margin that keeps
   integer frames off a tie) guards what the noise model does not
   describe: at fewer than four quantisation steps peak to peak the N samples are a
   deterministic staircase (phase error up to 1/(√2·B) rad, 0.35 rad at B = 2 DN,
   correlated between frequencies), and a pixel lit by stray light alone carries no fringe.

5. **Depth noise.** Right orders do not make a depth right: a pixel whose depth σ (the same
   sensor noise through ∂z/∂φ, ``ReconResult.sigma``) is large is wrong by more than
   ``gross_error_mm`` g (:data:`DEFAULT_GROSS_ERROR_MM`, 0.5 mm: the whole-field issue's
   definition of a wrong depth). A Gaussian depth error would do so with probability
   ``erfc(g/(σ√2))``, which gives the bound ``σ_z ≤ g / (√2·erfc⁻¹(rate))`` (0.102 mm for
   0.5 mm at 1e-6; :func:`max_depth_sigma_mm`). But the noise part of the depth error is the
   phase error θ of step 1 times ∂z/∂φ, and a depth error beyond g is a phase error beyond
   ``θ_g = g/|∂z/∂φ|`` — about a radian on a typical rig at that σ, where step 1's tails are
   far heavier than the Gaussian's: the phasor's tip must leave the wedge of half-angle θ_g,
   two half-planes at distance ``a·sin θ_g``, so ``P(|θ| > θ_g) ≤ 2·Q(a·sin θ_g)`` where the
   Gaussian says ``2·Q(a·θ_g)`` (at a = 5, θ_g = 1: 3·10⁻⁵ against 6·10⁻⁷). So the noise part
   is weighed by ``θ_g / sin θ_g`` (:func:`phasor_tail_factor_sq`; θ_g capped at π/2, where
   the bound becomes a ≥ the Gaussian's z) and pixels with
   ``√((σ_noise·θ_g/sin θ_g)² + σ_model²)`` beyond the bound are UNCERTAIN; ``sigma`` itself
   stays the 1-σ of the depth.

An explicit ``min_modulation`` (codes) replaces the whole rule (then only ``B_min ≥
min_modulation``). The rule is only as good as the noise model: a camera whose real noise
exceeds its model validates pixels at a higher order-error rate than the bound (the rate
grows like exp(−a²·sin²(·)/2) — e.g. a model 1.5× too optimistic at a_min turns 1e-6 into
about 1e-3; 1.2× gives 5e-5). Estimate the model from the data where possible
(:func:`app.recon.noise.estimate_sensor_noise`, N > 3; for N < 8 projector gamma inflates that
estimate, which errs on the safe side). Measured on the real CFPE captures (an 8-bit camera,
12 steps, residual beyond harmonics 1–4): σ_I ≈ 0.72 / 1.2–1.6 / 2.0–2.2 DN at A ≈ 10 / 50 /
100 DN, 1.3–1.7× :meth:`~app.recon.reconstructor.SensorNoise.typical` (0.56 / 0.96 / 1.31 DN).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from statistics import NormalDist

import numpy as np
import numpy.typing as npt

from app.core.schedule import DEFAULT_UNWRAP
from app.recon.phase import MODULATION_FLOOR_DN
from app.recon.unwrap import DEFAULT_CONSISTENCY_RAD, check_consistency_rad, unwrap_chain

#: Default bound on the probability that a pixel's fringe order is wrong and undetected.
DEFAULT_ORDER_ERROR_RATE = 1e-6
#: A depth error beyond this is a wrong depth, mm (acceptance: zero valid pixels beyond 0.5 mm).
DEFAULT_GROSS_ERROR_MM = 0.5

#: ``(θ/sin θ)² ≈ 1 + Σ_k c_k·t^k``, t = θ² ∈ [0, (π/2)²]: least squares on the exact function,
#: within 1.1e-4 of it (tests/recon/test_validity.py)
PHASOR_TAIL_COEFS = (0.33211458, 0.07104973, 0.00567615, 0.0035039)
#: θ_g is capped at π/2 (module docstring, step 5)
PHASOR_TAIL_T_MAX = (math.pi / 2.0) ** 2

F64 = npt.NDArray[np.float64]
_GRID = 4096  # samples of one wrapped phase over (−π, π]
_TWO_PI = 2.0 * math.pi


def phasor_phase_density(theta: npt.ArrayLike, snr: float) -> F64:
    """Density of the phase error of a phasor of SNR ``snr`` in circular Gaussian noise.

    Args:
        theta: phase errors, radians, in [−π, π] (any shape).
        snr: signal length / noise σ per component, ≥ 0.

    Returns:
        float64 density (1/rad) of ``theta``'s shape; integrates to 1 over (−π, π].
    """
    if not (math.isfinite(snr) and snr >= 0.0):
        raise ValueError(f"snr: must be finite and >= 0, got {snr}")
    t = np.asarray(theta, np.float64)
    x = snr * np.cos(t)
    phi = 0.5 * np.array([math.erfc(-v / math.sqrt(2.0)) for v in x.ravel()]).reshape(x.shape)
    return (math.exp(-0.5 * snr * snr) / _TWO_PI
            + x * np.exp(-0.5 * (snr * np.sin(t)) ** 2) * phi / math.sqrt(_TWO_PI))


def step_gains(frequencies: Sequence[float], method: str = DEFAULT_UNWRAP) -> F64:
    """The chain's error gains ``g_s`` (module docstring, step 2): (S − 1, K) float64, one row
    per rounding step (the first, absolute step rounds nothing)."""
    coefs, freqs = unwrap_chain(frequencies, method)
    rows = [(freqs[s] / freqs[s - 1]) * coefs[s - 1] - coefs[s] for s in range(1, len(freqs))]
    return np.asarray(rows, np.float64).reshape(-1, coefs.shape[1])


def undetected_order_error_rate(frequencies: Sequence[float], method: str = DEFAULT_UNWRAP, *,
                                consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
                                snr: float) -> float:
    """Σ over the unwrapping steps of P(order wrong and the consistency test passed), with every
    wrapped phase at phasor SNR ``snr`` (module docstring, steps 1–3)."""
    c = check_consistency_rad(consistency_rad)
    h = _TWO_PI / _GRID
    theta = (np.arange(_GRID) - _GRID // 2) * h  # [−π, π)
    dens = phasor_phase_density(theta, snr)
    total = 0.0
    for g in step_gains(frequencies, method):
        pdf = np.ones(1)
        for gk in g[np.abs(g) > 1e-12]:
            # the density of gk·θ sampled on the common grid of spacing h (mass conserved)
            half = int(math.ceil(abs(gk) * _GRID / 2))
            x = np.arange(-half, half + 1) * h
            scaled = np.interp(x / abs(gk), theta, dens, left=0.0, right=0.0) / abs(gk) * h
            scaled /= scaled.sum()
            n = pdf.size + scaled.size - 1
            nfft = 1 << (n - 1).bit_length()
            pdf = np.fft.irfft(np.fft.rfft(pdf, nfft) * np.fft.rfft(scaled, nfft), nfft)[:n]
        pdf = np.maximum(pdf, 0.0)
        d = (np.arange(pdf.size) - (pdf.size - 1) / 2) * h
        m = np.round(d / _TWO_PI)
        total += float(pdf[(m != 0) & (np.abs(d - _TWO_PI * m) < c)].sum())
    return total


@lru_cache(maxsize=64)
def _min_snr(frequencies: tuple[float, ...], method: str, consistency_rad: float,
             rate: float) -> float:
    lo, hi = 0.5, 200.0
    if undetected_order_error_rate(frequencies, method, consistency_rad=consistency_rad,
                                   snr=hi) > rate:
        return hi
    for _ in range(40):  # bisection in log a: 40 halvings of a factor 400 → 1e-10 relative
        mid = math.sqrt(lo * hi)
        if undetected_order_error_rate(frequencies, method, consistency_rad=consistency_rad,
                                       snr=mid) > rate:
            lo = mid
        else:
            hi = mid
    return hi


def min_phasor_snr(frequencies: Sequence[float], method: str = DEFAULT_UNWRAP, *,
                   consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
                   rate: float = DEFAULT_ORDER_ERROR_RATE) -> float:
    """The least phasor SNR ``a_min`` = B·√(N/2)/σ_I at which the schedule's undetected
    order-error probability is ≤ ``rate`` (module docstring).

    Args:
        frequencies: the schedule's fringe counts, increasing.
        method: ``"hierarchical"`` or ``"heterodyne"``.
        consistency_rad: the unwrapping consistency threshold, (0, π] rad.
        rate: the bound per pixel, in (0, 0.1].

    Returns:
        ``a_min`` (dimensionless, cached per schedule).
    """
    if not (math.isfinite(rate) and 0.0 < rate <= 0.1):
        raise ValueError(f"rate: must be in (0, 0.1], got {rate}")
    c = check_consistency_rad(consistency_rad)
    return _min_snr(tuple(float(k) for k in frequencies), method, c, float(rate))


def modulation_threshold(background_dn: npt.ArrayLike, steps: int, snr: float, read_var_dn2: float,
                         gain_dn_per_e: float, floor_dn: float = MODULATION_FLOOR_DN) -> F64:
    """Per-pixel least modulation B of the rule (module docstring, step 4), codes.

    Args:
        background_dn: mean intensity A of the pixel, codes (any shape).
        steps: phase steps N ≥ 3.
        snr: ``a_min`` of :func:`min_phasor_snr`.
        read_var_dn2, gain_dn_per_e: the camera's noise model, σ_I² = read_var + gain·A.
        floor_dn: the least threshold, codes.

    Returns:
        float64 threshold of ``background_dn``'s shape.
    """
    a = np.maximum(np.asarray(background_dn, np.float64), 0.0)
    var = read_var_dn2 + gain_dn_per_e * a
    return np.maximum(floor_dn, snr * np.sqrt(2.0 / steps * var))


def max_depth_sigma_mm(gross_error_mm: float = DEFAULT_GROSS_ERROR_MM,
                       rate: float = DEFAULT_ORDER_ERROR_RATE) -> float:
    """The largest depth σ (mm) at which a Gaussian depth error exceeds ``gross_error_mm`` with
    probability ≤ ``rate``: ``g / (√2·erfc⁻¹(rate))`` (module docstring, step 5).

    Args:
        gross_error_mm: the error that makes a depth wrong, mm, > 0.
        rate: the bound per pixel, in (0, 0.1].
    """
    if not (math.isfinite(gross_error_mm) and gross_error_mm > 0.0):
        raise ValueError(f"gross_error_mm: must be finite and > 0, got {gross_error_mm}")
    if not (math.isfinite(rate) and 0.0 < rate <= 0.1):
        raise ValueError(f"rate: must be in (0, 0.1], got {rate}")
    # √2·erfc⁻¹(rate) = Φ⁻¹(1 − rate/2)
    return gross_error_mm / NormalDist().inv_cdf(1.0 - rate / 2.0)


def phasor_tail_factor_sq(theta_sq: npt.ArrayLike) -> F64:
    """``(θ_g / sin θ_g)²`` for the squared phase error ``theta_sq`` (rad²) that makes a depth
    wrong, θ_g capped at π/2 (module docstring, step 5): the weight of a pixel's noise variance
    in the gross-error test. 1 at 0; NaN stays NaN.

    Args:
        theta_sq: θ_g² (rad², ≥ 0; any shape; +inf: the cap).

    Returns:
        float64 array of ``theta_sq``'s shape, in [1, (π/2)²].
    """
    t = np.asarray(theta_sq, np.float64)
    if np.any(t < 0):
        raise ValueError("theta_sq: must be >= 0")
    t = np.minimum(t, PHASOR_TAIL_T_MAX)
    c1, c2, c3, c4 = PHASOR_TAIL_COEFS
    return np.asarray(1.0 + t * (c1 + t * (c2 + t * (c3 + t * c4))), np.float64)
