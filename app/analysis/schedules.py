"""Predicted depth noise and fringe-order error rate of a pattern schedule at a rig's noise.

The chain (Zuo et al., "Temporal phase unwrapping algorithms for fringe projection
profilometry: a comparative review", Opt. Lasers Eng. 85, 84–103, 2016, Sec. 3–4):

1. Wrapped phase of one frequency from N steps: σ_φ = √(2/N)·σ_I/B (σ_I the intensity
   noise per frame, B the modulation; independent between frequencies).
2. Unwrapping step s (:func:`app.recon.unwrap.unwrap_chain`: step phases are integer
   combinations ``c_s · φ_w`` of the wrapped phases, of ``f_s`` fringes): the rounding
   argument ``(f_s/f_{s−1})·φ_{s−1} − φ_s`` has, with every earlier order right, the error
   ``(r_s c_{s−1} − c_s) · n`` (n the wrapped-phase errors), so its σ is
   ``σ_s = √(Σ_k (r_s c_{s−1,k} − c_{s,k})² σ_{φ,k}²)``. The order is wrong when that error
   leaves (−π, π): probability ``erfc(π / (σ_s √2))`` (Gaussian tail). Hierarchical
   chains (c = identity) give the textbook ``σ_s = √(r_s² σ_{s−1}² + σ_s²)``.
3. Depth: the finest phase is the finest wrapped phase plus 2π·order, so with right orders
   ``σ_z = |∂z/∂φ|·σ_φ,finest`` (the calibration's slope, or the twin's nominal).

Everything here is pure numpy; the service evaluates it per pixel of the latest live set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.special import erfc

from app.core.schedule import PatternSchedule
from app.recon.unwrap import unwrap_chain

F64 = npt.NDArray[np.float64]

__all__ = ["SchedulePrediction", "order_error_probability", "predict_schedule", "step_sigmas_rad",
           "wrapped_phase_sigma_rad"]


def wrapped_phase_sigma_rad(sigma_i: npt.ArrayLike, modulation: npt.ArrayLike, steps: int) -> F64:
    """σ_φ = √(2/N)·σ_I/B of the N-step wrapped phase, radians (NaN where B ≤ 0 or not finite).

    Args:
        sigma_i: intensity noise per frame, codes; any shape broadcasting with ``modulation``.
        modulation: modulation B, codes.
        steps: phase steps N ≥ 3.
    """
    if int(steps) != steps or steps < 3:
        raise ValueError(f"steps: need an integer N >= 3, got {steps}")
    b = np.asarray(modulation, np.float64)
    s = np.asarray(sigma_i, np.float64)
    if np.any(s < 0):
        raise ValueError("sigma_i: must be >= 0")
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(b > 0, s * math.sqrt(2.0 / steps) / b, np.nan)


def step_sigmas_rad(schedule: PatternSchedule, sigma_phi_rad: npt.ArrayLike) -> F64:
    """σ of the rounding argument at every unwrapping step after the absolute one, radians.

    Args:
        schedule: the pattern schedule (its frequencies and unwrapping method).
        sigma_phi_rad: σ of each wrapped phase, shape (K,) or (K, ...) per frequency, or one
            value (or array without the K axis) shared by all K frequencies.

    Returns:
        float64 (S − 1, ...) with S the chain's steps (:func:`~app.recon.unwrap.unwrap_chain`).
    """
    if not isinstance(schedule, PatternSchedule):
        raise ValueError("schedule: expected a PatternSchedule")
    coefs, freqs = unwrap_chain(schedule.frequencies, schedule.unwrap)
    k = len(schedule.frequencies)
    sig = np.asarray(sigma_phi_rad, np.float64)
    if sig.ndim == 0 or sig.shape[0] != k:
        sig = np.broadcast_to(sig, (k, *sig.shape))
    var = sig**2
    out = []
    for s in range(1, len(freqs)):
        w = (freqs[s] / freqs[s - 1]) * coefs[s - 1] - coefs[s]
        out.append(np.sqrt(np.tensordot(w**2, var, axes=1)))
    return np.asarray(out, np.float64)


def order_error_probability(schedule: PatternSchedule, sigma_phi_rad: npt.ArrayLike) -> F64:
    """Probability that a pixel's finest fringe order is wrong: 1 − Π_s (1 − erfc(π/(σ_s√2))).

    Args: as :func:`step_sigmas_rad`. Returns float64 of the per-pixel shape (a 0-d array for
    scalars). The first (absolute) step has no order to get wrong.
    """
    steps = step_sigmas_rad(schedule, sigma_phi_rad)
    with np.errstate(divide="ignore"):
        p_step = erfc(math.pi / (steps * math.sqrt(2.0)))
    return np.asarray(1.0 - np.prod(1.0 - p_step, axis=0), np.float64)


@dataclass(frozen=True)
class SchedulePrediction:
    """Predicted figures of one schedule over a set of pixels.

    Attributes:
        sigma_mm: median per-pixel depth σ, mm (|∂z/∂φ|·σ_φ of the finest pattern).
        sigma_phi_rad: median σ_φ of the finest wrapped phase, rad.
        order_error_rate: mean over the pixels of the probability of a wrong fringe order.
        worst_step_sigma_rad: the 99th percentile of the largest unwrapping-step σ, rad
            (order errors start where this nears π/3; the consistency check rejects at π/2).
    """

    sigma_mm: float
    sigma_phi_rad: float
    order_error_rate: float
    worst_step_sigma_rad: float


def predict_schedule(schedule: PatternSchedule, sigma_i: npt.ArrayLike, modulation: npt.ArrayLike,
                     dz_dphi_mm_per_rad: npt.ArrayLike) -> SchedulePrediction:
    """Depth σ and order-error rate of ``schedule`` over pixels with the given
    noise, contrast and slope.

    Args:
        schedule: the pattern schedule.
        sigma_i: intensity noise σ_I per frame, codes, (P,) or scalar.
        modulation: modulation B, codes, (P,) — the same at every frequency (the fringe
            contrast of the finest pattern: a coarser one is at least as sharp).
        dz_dphi_mm_per_rad: |∂z/∂φ| of the finest phase, mm/rad, (P,) or scalar.

    Returns:
        :class:`SchedulePrediction`; pixels with a non-finite σ_φ or slope are left out.
    """
    sig_phi = wrapped_phase_sigma_rad(sigma_i, modulation, schedule.steps)
    slope = np.abs(np.asarray(dz_dphi_mm_per_rad, np.float64))
    sig_phi, slope = np.broadcast_arrays(np.atleast_1d(sig_phi), np.atleast_1d(slope))
    keep = np.isfinite(sig_phi) & np.isfinite(slope)
    if not keep.any():
        raise ValueError("modulation: no pixel with a finite phase noise and slope")
    sp, sl = sig_phi[keep], slope[keep]
    worst = step_sigmas_rad(schedule, sp)
    worst_p99 = float(np.percentile(worst.max(axis=0), 99)) if worst.size else 0.0
    return SchedulePrediction(
        sigma_mm=float(np.median(sl * sp)),
        sigma_phi_rad=float(np.median(sp)),
        order_error_rate=float(np.mean(order_error_probability(schedule, sp))),
        worst_step_sigma_rad=worst_p99,
    )
