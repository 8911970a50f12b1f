"""Phase-error lookup table: the projector-gamma (harmonic) error of few-step phase, learned from data.

A projector with gamma ≠ 1 adds harmonics to the fringes; an N-step decoder aliases
harmonics N ± 1 onto the fundamental, so its wrapped phase carries a periodic error of
period 2π/N in φ itself (for N = 4 mostly ``a sin 4φ``). The error depends on the
projector (and the defocus of the harmonics), not on the scene's albedo, so it can be
learned once and subtracted: Zhang & Huang, "Phase error compensation for a 3-D shape
measurement system based on the phase-shifting method", Opt. Eng. 46(6) 063601 (2007).
Here the table is learned per frequency against a reference phase of many more steps
(whose harmonic error is far smaller) on one scene and applied to others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

TWO_PI = 2.0 * math.pi
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PhaseErrorLUT:
    """Mean wrapped-phase error per frequency as a function of the wrapped phase.

    Attributes:
        error_rad: (K, bins) float64, the error at bin centres ``(i + 0.5)·2π/bins``, radians.
    """

    error_rad: F64

    @classmethod
    def fit(cls, wrapped: npt.ArrayLike, reference: npt.ArrayLike, mask: npt.ArrayLike | None = None,
            *, bins: int = 128) -> PhaseErrorLUT:
        """Learn the table from a few-step phase and a reference phase of the same scene.

        Args:
            wrapped: (K, H, W) wrapped phases to correct, radians in [0, 2π).
            reference: (K, H, W) reference wrapped phases (e.g. 12-step), radians.
            mask: (H, W) bool, pixels to learn from (valid in both); default all.
            bins: table entries per frequency, ≥ 8.

        Returns:
            :class:`PhaseErrorLUT` (bins without samples hold 0).
        """
        w = np.asarray(wrapped, dtype=np.float64)
        ref = np.asarray(reference, dtype=np.float64)
        if w.ndim != 3 or ref.shape != w.shape:
            raise ValueError(f"reference: shape {ref.shape} must equal wrapped shape {w.shape} (K, H, W)")
        if int(bins) != bins or bins < 8:
            raise ValueError(f"bins: need an integer >= 8, got {bins}")
        m = np.ones(w.shape[1:], bool) if mask is None else np.asarray(mask, dtype=bool)
        if m.shape != w.shape[1:]:
            raise ValueError(f"mask: shape {m.shape} must be {w.shape[1:]}")
        err = np.angle(np.exp(1j * (w - ref)))
        table = np.zeros((w.shape[0], bins))
        for k in range(w.shape[0]):
            idx = np.floor(w[k][m] * (bins / TWO_PI)).astype(np.int64) % bins
            total = np.bincount(idx, err[k][m], bins)
            count = np.bincount(idx, None, bins)
            table[k] = total / np.maximum(count, 1)
        return cls(table)

    def apply(self, wrapped: npt.ArrayLike) -> F64:
        """Corrected wrapped phases: ``wrapped − error(wrapped)`` (linear interpolation, circular), in [0, 2π).

        Args:
            wrapped: (K, H, W) wrapped phases, radians, K = the table's frequencies.
        """
        w = np.asarray(wrapped, dtype=np.float64)
        k_n, bins = self.error_rad.shape
        if w.ndim != 3 or w.shape[0] != k_n:
            raise ValueError(f"wrapped: expected shape ({k_n}, H, W), got {w.shape}")
        out = np.empty_like(w)
        for k in range(k_n):
            x = w[k] * (bins / TWO_PI) - 0.5
            i0 = np.floor(x).astype(np.int64)
            t = x - i0
            corr = (1.0 - t) * self.error_rad[k][i0 % bins] + t * self.error_rad[k][(i0 + 1) % bins]
            out[k] = np.mod(w[k] - corr, TWO_PI)
        out[out >= TWO_PI] = 0.0
        return out
