"""Hierarchical temporal phase unwrapping (Le et al. 2018) with a consistency check.

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


def _check_frequencies(frequencies: Sequence[int], n: int) -> list[int]:
    freqs = [int(k) for k in frequencies]
    if len(freqs) != n:
        raise ValueError(f"frequencies: {len(freqs)} given for {n} phase maps")
    if not freqs or freqs[0] != 1 or any(b <= a for a, b in zip(freqs, freqs[1:], strict=False)):
        raise ValueError(f"frequencies: need 1 = k_0 < k_1 < ..., got {freqs}")
    return freqs


def unwrap_hierarchical(
    wrapped: npt.ArrayLike,
    frequencies: Sequence[int],
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
    unwrapped: npt.ArrayLike, modulation: npt.ArrayLike, frequencies: Sequence[int], steps: int
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
    freqs = _check_frequencies(frequencies, phi.shape[0])
    k = np.asarray(freqs, dtype=np.float64)[:, None, None]
    weight = steps * mod**2 * k**2
    wsum = weight.sum(axis=0)
    est = (weight * (k[-1] / k) * phi).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(wsum > 0.0, est / np.where(wsum > 0.0, wsum, 1.0), np.nan)
