"""Temporal phase unwrapping with a consistency check: hierarchical (Le et al. 2018) and heterodyne.

The k = 1 phase is absolute. Each finer frequency k_n takes its fringe order from the
previous unwrapped phase scaled by the frequency ratio:

    e      = (k_n / k_{n−1}) · φ_uw(k_{n−1}) − φ_w(k_n)
    m      = round(e / 2π)
    φ_uw   = φ_w(k_n) + 2π m

With correct orders the residual ``d = e − 2π m`` is pure noise, ≈ (k_n/k_{n−1})·σ_{n−1};
once |d| approaches π the rounding can pick the neighbouring order. A pixel is
*consistent* only if |d| < ``consistency_rad`` at every step. The default π/2 sits
at half the ambiguity distance: for a well-modulated pixel |d| is ≈ 0.1 rad, so the
test rejects only pixels whose noise is already within a factor 2 of an order error
(such pixels are marked invalid, never guessed).

Heterodyne (multi-wavelength) schedules have no single-fringe pattern. Beats of two
wrapped phases, ``wrap(φ_b − φ_a)``, behave like a pattern of ``k_b − k_a`` fringes;
beats of beats shrink further until one spans at most one fringe over the field (it is
absolute). That phase then unwraps, by the same rounding rule and check, the highest
beat of each level down to the finest pattern (Towers et al., Opt. Lett. 28(11) 887,
2003; Reich et al., Opt. Eng. 36(5), 1997). :func:`unwrap_chain` lists the steps as
integer combinations of the wrapped phases; the hierarchical chain is the identity.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

TWO_PI = 2.0 * math.pi
DEFAULT_CONSISTENCY_RAD = 0.5 * math.pi

F64 = npt.NDArray[np.float64]


def check_consistency_rad(consistency_rad: float) -> float:
    """Validate the unwrapping threshold: 0 < value ≤ π radians."""
    if not (math.isfinite(consistency_rad) and 0.0 < consistency_rad <= math.pi):
        raise ValueError(f"consistency_rad: must be in (0, π], got {consistency_rad}")
    return float(consistency_rad)


def _check_frequencies(frequencies: Sequence[float], n: int, *, first_one: bool = True) -> list[float]:
    freqs = [float(k) for k in frequencies]
    if len(freqs) != n:
        raise ValueError(f"frequencies: {len(freqs)} given for {n} phase maps")
    if not freqs or any(b <= a for a, b in zip(freqs, freqs[1:], strict=False)) or freqs[0] <= 0:
        raise ValueError(f"frequencies: need 0 < k_0 < k_1 < ..., got {freqs}")
    if first_one and freqs[0] != 1:
        raise ValueError(f"frequencies: need 1 = k_0 < k_1 < ..., got {freqs}")
    return freqs


def unwrap_chain(frequencies: Sequence[float], method: str = "hierarchical") -> tuple[F64, F64]:
    """The unwrapping steps of a schedule as combinations of its wrapped phases.

    Args:
        frequencies: the K fringe counts, increasing.
        method: ``"hierarchical"`` (k_0 = 1; the chain is the identity) or
            ``"heterodyne"`` (K ≥ 3; beats of neighbouring frequencies, level by level).

    Returns:
        ``(coefs, freqs)``: (S, K) float64 integer coefficients and (S,) fringe counts;
        step ``s`` is the phase ``wrap(coefs[s] · φ_w)`` of ``freqs[s]`` fringes. Step 0
        spans at most one fringe (absolute); the last is the finest pattern itself.
    """
    if method == "hierarchical":
        freqs = _check_frequencies(frequencies, len(frequencies))
        return np.eye(len(freqs)), np.asarray(freqs)
    if method != "heterodyne":
        raise ValueError(f"unwrap: must be 'hierarchical' or 'heterodyne', got {method!r}")
    freqs = _check_frequencies(frequencies, len(frequencies), first_one=False)
    n = len(freqs)
    if n < 3:
        raise ValueError(f"frequencies: heterodyne unwrapping needs at least 3, got {n}")
    level = [(f, np.eye(n)[i]) for i, f in enumerate(freqs)]
    tops = [level[-1]]
    while level[0][0] > 1.0 + 1e-9:
        if len(level) < 2:
            raise ValueError(f"frequencies: {freqs} beat down to {level[0][0]:.4g} fringes, not <= 1 (not absolute)")
        beats = []
        for (fa, ca), (fb, cb) in zip(level, level[1:], strict=False):
            beats.append((fb - fa, cb - ca) if fb >= fa else (fa - fb, ca - cb))
        level = sorted(beats, key=lambda b: b[0])
        if level[0][0] < 1e-6:
            raise ValueError(f"frequencies: {freqs} give a zero beat (two equal differences)")
        tops.append(level[-1])
    steps = [level[0], *([] if len(level) == 1 else tops[-1:]), *reversed(tops[:-1])]
    return np.stack([c for _, c in steps]), np.asarray([f for f, _ in steps])


def unwrap_phases(
    wrapped: npt.ArrayLike,
    frequencies: Sequence[float],
    method: str = "hierarchical",
    *,
    consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Unwrap every frequency, hierarchically or by heterodyne beats (see :func:`unwrap_chain`).

    Args:
        wrapped: (K, H, W) wrapped phases in [0, 2π), radians.
        frequencies: the K fringe counts, increasing.
        method: ``"hierarchical"`` or ``"heterodyne"``.
        consistency_rad: largest accepted |residual − rounded residual| at every step, (0, π].

    Returns:
        ``(unwrapped, consistent)`` as :func:`unwrap_hierarchical`. For heterodyne, the
        finest phase comes from the chain and every other from it by the frequency ratio;
        a pixel is also inconsistent when its absolute beat phase lies outside the field,
        [−s, 2π·f0 + s] with s = ``consistency_rad``·f0/f1.
    """
    wrapped = np.asarray(wrapped, dtype=np.float64)
    if wrapped.ndim != 3:
        raise ValueError(f"wrapped: expected shape (K, H, W), got {wrapped.shape}")
    if method == "hierarchical":
        return unwrap_hierarchical(wrapped, frequencies, consistency_rad=consistency_rad)
    coefs, steps = unwrap_chain(frequencies, method)
    if len(frequencies) != wrapped.shape[0]:
        raise ValueError(f"frequencies: {len(frequencies)} given for {wrapped.shape[0]} phase maps")
    threshold = check_consistency_rad(consistency_rad)
    prev = absolute_phase(np.mod(np.tensordot(coefs[0], wrapped, axes=1), TWO_PI), steps[0])
    # the absolute beat covers 2π·f0 of the circle; beyond it (by more than the first step
    # tolerates) lies no point of the field: noise, not fringes
    slack = threshold * steps[0] / steps[1]
    consistent = (prev >= -slack) & (prev <= TWO_PI * steps[0] + slack)
    for s in range(1, len(steps)):
        phw = np.mod(np.tensordot(coefs[s], wrapped, axes=1), TWO_PI)
        e = (steps[s] / steps[s - 1]) * prev - phw
        order = np.floor(e / TWO_PI + 0.5)
        consistent &= np.abs(e - TWO_PI * order) < threshold
        prev = phw + TWO_PI * order
    freqs = np.asarray(frequencies, dtype=np.float64)
    out = np.empty_like(wrapped)
    for i in range(len(freqs) - 1):
        e = (freqs[i] / freqs[-1]) * prev - wrapped[i]
        out[i] = wrapped[i] + TWO_PI * np.floor(e / TWO_PI + 0.5)
    out[-1] = prev
    return out, consistent


def absolute_phase(wrapped: npt.ArrayLike, fringes: float) -> F64:
    """The phase of a pattern of ``fringes`` ≤ 1 over the field: values in the unused part of
    the circle (beyond 2π·fringes, from noise at the field's start) are moved below 0 by
    splitting that gap in half. For one fringe the phase is returned unchanged."""
    wrapped = np.asarray(wrapped, dtype=np.float64)
    return np.where(wrapped > math.pi * (1.0 + fringes), wrapped - TWO_PI, wrapped)


def unwrap_hierarchical(
    wrapped: npt.ArrayLike,
    frequencies: Sequence[float],
    *,
    consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Unwrap every frequency hierarchically.

    Args:
        wrapped: (K, H, W) wrapped phases, radians; ``wrapped[0]`` (k = 1) in [0, 2π).
        frequencies: the K fringe counts, ``frequencies[0] == 1``, increasing.
        consistency_rad: largest accepted |residual − rounded residual|, radians, (0, π].

    Returns:
        ``(unwrapped, consistent)``: (K, H, W) float64 absolute phases
        (``unwrapped[i] ≈ 2π k_i x / w``) and an (H, W) bool mask of pixels whose every
        rounding step passed the check.
    """
    wrapped = np.asarray(wrapped, dtype=np.float64)
    if wrapped.ndim != 3:
        raise ValueError(f"wrapped: expected shape (K, H, W), got {wrapped.shape}")
    freqs = _check_frequencies(frequencies, wrapped.shape[0])
    threshold = check_consistency_rad(consistency_rad)
    out = np.empty_like(wrapped)
    out[0] = wrapped[0]
    consistent = np.ones(wrapped.shape[1:], dtype=bool)
    for i in range(1, len(freqs)):
        e = (freqs[i] / freqs[i - 1]) * out[i - 1] - wrapped[i]
        order = np.floor(e / TWO_PI + 0.5)  # round half up, the same rule as the fast path
        consistent &= np.abs(e - TWO_PI * order) < threshold
        out[i] = wrapped[i] + TWO_PI * order
    return out, consistent


def combine_frequencies(
    unwrapped: npt.ArrayLike, modulation: npt.ArrayLike, frequencies: Sequence[float], steps: int
) -> F64:
    """Noise-optimal phase from all frequencies, in the finest frequency's units.

    Each unwrapped map estimates the finest phase as ``(k_max/k_i)·φ_i`` with variance
    ∝ (k_max/k_i)² / (N·B_i²); inverse-variance weighting gives weights ∝ N·B_i²·k_i².

    Args:
        unwrapped: (K, H, W) absolute phases, radians.
        modulation: (K, H, W) modulation B per frequency, codes.
        frequencies: the K fringe counts.
        steps: phase shifts N per frequency.

    Returns:
        (H, W) float64 phase of the finest frequency, radians (NaN where all B are 0).
    """
    phi = np.asarray(unwrapped, dtype=np.float64)
    mod = np.asarray(modulation, dtype=np.float64)
    if phi.ndim != 3 or mod.shape != phi.shape:
        raise ValueError(f"modulation: shape {mod.shape} must equal unwrapped shape {phi.shape}")
    freqs = _check_frequencies(frequencies, phi.shape[0], first_one=False)
    k = np.asarray(freqs, dtype=np.float64)[:, None, None]
    weight = steps * mod**2 * k**2
    wsum = weight.sum(axis=0)
    est = (weight * (k[-1] / k) * phi).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(wsum > 0.0, est / np.where(wsum > 0.0, wsum, 1.0), np.nan)
