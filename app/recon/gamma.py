"""Phase-error lookup table: the projector-gamma (harmonic) error of few-step phase, learned from
data.

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

import hashlib
import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

TWO_PI = 2.0 * math.pi
F64 = npt.NDArray[np.float64]
#: ``format`` of a saved table (``fringescope gamma``)
LUT_FORMAT = "fringescope-phase-error"
#: the most a table's Fourier series may differ from the table (its linear interpolation, as
#: :meth:`PhaseErrorLUT.apply` reads it) anywhere on the circle, rad; a table whose series does
#: not reach it is applied as a table
SERIES_MAX_DEV_RAD = 1e-4
#: the most harmonics of the table's period a series keeps (what the fused kernel evaluates)
SERIES_MAX_HARMONICS = 3
#: points per table bin at which the series is fitted to the table and checked against it (bin
#: centres included): the largest |series − table| between two of them exceeds theirs by at most
#: |e''|·(π/(4·bins))²/2, < 10⁻⁶ rad for the tables here
SERIES_SAMPLES_PER_BIN = 4


@dataclass(frozen=True, eq=False)
class PhaseErrorSeries:
    """A phase-error table as a short Fourier series of the wrapped phase φ:

        e(φ) = a_0 + Σ_{j=1..J} a_j cos(jPφ) + b_j sin(jPφ)

    in the harmonics of the table's period 2π/P (P = N for an N-step decoder: its gamma error
    repeats every 2π/N). Evaluated from the pixel's unit phasor (cos φ, sin φ) by complex
    multiplication, it needs neither φ nor a table look-up, so the fused kernel's pixel loop
    stays vectorised (:func:`app.recon.fast._series_error`).

    Attributes:
        coefficients: (K, 1 + 2J) float64 per frequency (a_0, a_1, b_1, …, a_J, b_J), rad.
        period: P, the harmonic the series' terms are multiples of.
        max_dev_rad: the largest |series − table| found on the fitting grid, rad.
    """

    coefficients: F64
    period: int
    max_dev_rad: float

    @property
    def harmonics(self) -> int:
        """J, the harmonics of the period kept."""
        return int(self.coefficients.shape[1] - 1) // 2

    def error_at(self, wrapped: npt.ArrayLike) -> F64:
        """The series at the phases ``wrapped`` (K, …) (radians; row k by frequency k's
        coefficients), rad, float64."""
        w = np.asarray(wrapped, dtype=np.float64)
        if w.shape[:1] != self.coefficients.shape[:1]:
            raise ValueError(f"wrapped: expected {self.coefficients.shape[0]} rows, "
                             f"got shape {w.shape}")
        out = np.empty_like(w)
        for k in range(w.shape[0]):
            c = self.coefficients[k]
            out[k] = c[0]
            for j in range(1, self.harmonics + 1):
                arg = (j * self.period) * w[k]
                out[k] += c[2 * j - 1] * np.cos(arg) + c[2 * j] * np.sin(arg)
        return out

    def kernel_coefficients(self, harmonics: int = SERIES_MAX_HARMONICS) -> npt.NDArray[np.float32]:
        """(K, 1 + 2·``harmonics``) float32 :attr:`coefficients` padded with zeros: the fused
        kernel evaluates a fixed number of harmonics."""
        if self.harmonics > harmonics:
            raise ValueError(f"harmonics: the series has {self.harmonics}, more than {harmonics}")
        out = np.zeros((self.coefficients.shape[0], 1 + 2 * harmonics), np.float32)
        out[:, :self.coefficients.shape[1]] = self.coefficients
        return out


def _interpolate(error_rad: F64, wrapped: F64) -> F64:
    """(K, …) the tables ``error_rad`` (K, bins) at the phases ``wrapped`` (…) rad in [0, 2π):
    linear interpolation between bin centres, circular (what :meth:`PhaseErrorLUT.apply`
    corrects by)."""
    bins = error_rad.shape[1]
    x = wrapped * (bins / TWO_PI) - 0.5
    i0 = np.floor(x).astype(np.int64)
    t = x - i0
    return np.asarray((1.0 - t) * error_rad[:, i0 % bins] + t * error_rad[:, (i0 + 1) % bins],
                      np.float64)


def fit_series(error_rad: F64, period: int, *, max_dev_rad: float = SERIES_MAX_DEV_RAD,
               harmonics: int = SERIES_MAX_HARMONICS) -> PhaseErrorSeries | None:
    """The Fourier series in the first ``harmonics`` harmonics of ``period`` that best
    reproduces the tables, if it reproduces them to ``max_dev_rad``.

    The coefficients are the least-squares projection of the tables' linear interpolation
    (sampled :data:`SERIES_SAMPLES_PER_BIN` times per bin, bin centres included) onto
    1, cos(jPφ), sin(jPφ), j = 1..J. All J = ``harmonics`` are kept even where fewer would
    pass: the fused kernel evaluates that many whatever the coefficients (zeros included), so
    the more accurate series costs nothing.

    Args:
        error_rad: (K, bins) float64 tables, rad (:attr:`PhaseErrorLUT.error_rad`).
        period: P ≥ 1.
        max_dev_rad: the tolerance on every row's largest |series − table| on those samples, rad.
        harmonics: J ≥ 0.

    Returns:
        :class:`PhaseErrorSeries`, or None where the series misses the tolerance (a noisy or
        sharp table: apply it as a table) or J·P reaches the table's Nyquist harmonic.
    """
    bins = error_rad.shape[1]
    if period < 1 or harmonics * period >= bins // 2:
        return None
    n_samples = SERIES_SAMPLES_PER_BIN * bins
    phase = np.arange(n_samples) * (TWO_PI / n_samples)
    table = _interpolate(error_rad, phase)
    # (K, n/2 + 1) complex: the mean of table·e^{−ihφ}; a_h = 2·Re, b_h = −2·Im for h > 0
    spectrum = np.fft.rfft(table, axis=1) / n_samples
    coefs = [spectrum[:, 0].real]
    series = np.repeat(coefs[0][:, None], n_samples, axis=1)
    for j in range(1, harmonics + 1):
        h = j * period
        a, b = 2.0 * spectrum[:, h].real, -2.0 * spectrum[:, h].imag
        coefs += [a, b]
        series = series + a[:, None] * np.cos(h * phase) + b[:, None] * np.sin(h * phase)
    dev = float(np.abs(series - table).max())
    if dev > max_dev_rad:
        return None
    return PhaseErrorSeries(np.stack(coefs, axis=1), int(period), dev)


@dataclass(frozen=True, eq=False)
class PhaseErrorLUT:
    """Mean wrapped-phase error per frequency as a function of the wrapped phase.

    Attributes:
        error_rad: (K, bins) float64, the error at bin centres ``(i + 0.5)·2π/bins``, radians.
    """

    error_rad: F64
    #: the N of the decoder the table corrects, and the fringe counts it was learned at
    #: (empty / 0 when not recorded); :meth:`check_schedule` refuses another schedule
    steps: int = 0
    frequencies: tuple[float, ...] = field(default=())

    @classmethod
    def fit(cls, wrapped: npt.ArrayLike, reference: npt.ArrayLike,
            mask: npt.ArrayLike | None = None, *, bins: int = 128) -> PhaseErrorLUT:
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
            raise ValueError(f"reference: shape {ref.shape} must equal wrapped shape {w.shape} "
                             "(K, H, W)")
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

    @classmethod
    def learn(cls, frames: npt.ArrayLike, reference_steps: int, steps: int, *,
              frequencies: tuple[float, ...] = (), max_code: int | None = None,
              min_modulation: float = 10.0, bins: int = 128) -> PhaseErrorLUT:
        """Learn the ``steps``-step table from one capture with ``reference_steps`` shifts.

        The ``steps``-step subset (every ``reference_steps // steps``-th shift) is decoded
        and compared with the phase of all shifts, whose harmonic error is far smaller
        (an N-step decoder is blind to harmonics below N − 1).

        Args:
            frames: (K·reference_steps, H, W) uint8/uint16, frequency-major, shift-minor.
            reference_steps: shifts per frequency in ``frames``; a multiple of ``steps``.
            steps: the N of the decoder to correct, ≥ 3.
            frequencies: the K fringe counts (recorded in the table), or ().
            max_code: saturation code (default by dtype); clipped pixels are not learned from.
            min_modulation: reference modulation below this (codes) is not learned from.
            bins: table entries per frequency.
        """
        from app.recon.phase import wrapped_phase

        a = np.asarray(frames)
        if int(steps) != steps or steps < 3:
            raise ValueError(f"steps: need an integer N >= 3, got {steps}")
        if (int(reference_steps) != reference_steps or reference_steps % steps
                or reference_steps <= steps):
            raise ValueError(f"reference_steps: {reference_steps} must be a larger multiple of "
                             f"steps={steps}")
        if a.ndim != 3 or a.shape[0] % reference_steps:
            raise ValueError(f"frames: expected (K·{reference_steps}, H, W), got shape {a.shape}")
        k_n = a.shape[0] // reference_steps
        if frequencies and len(frequencies) != k_n:
            raise ValueError(f"frequencies: {len(frequencies)} given for {k_n} frequencies in "
                             "frames")
        stride = reference_steps // steps
        per_freq = a.reshape(k_n, reference_steps, *a.shape[1:])
        subset = per_freq[:, ::stride].reshape(k_n * steps, *a.shape[1:])
        ref = wrapped_phase(a, reference_steps, max_code=max_code)
        few = wrapped_phase(subset, steps, max_code=max_code)
        clipped = ref.saturated if ref.recovered is None else ref.saturated | ref.recovered
        mask = (ref.modulation.min(axis=0) >= min_modulation) & ~clipped
        if not mask.any():
            raise ValueError("frames: no pixel has reference modulation >= "
                             f"{min_modulation:g} codes without clipping; nothing to learn from")
        lut = cls.fit(few.phase, ref.phase, mask, bins=bins)
        return cls(lut.error_rad, int(steps), tuple(float(k) for k in frequencies))

    def check_schedule(self, steps: int, frequencies: tuple[float, ...]) -> None:
        """Raise ``ValueError`` (naming the key) unless the table fits a schedule."""
        if self.steps and steps != self.steps:
            raise ValueError(f"steps: the phase-error table corrects {self.steps}-step phase, "
                             f"the set has {steps}")
        if len(frequencies) != self.error_rad.shape[0] or (
                self.frequencies and not np.allclose(self.frequencies, frequencies, rtol=1e-9)):
            want = list(self.frequencies) or f"{self.error_rad.shape[0]} frequencies"
            raise ValueError(f"frequencies: the phase-error table was learned at {want}, "
                             "the set has "
                             f"{list(frequencies)}")

    def amplitude_rad(self) -> F64:
        """(K,) RMS of the table per frequency, radians (the error it removes)."""
        return np.asarray(np.sqrt(np.mean(self.error_rad**2, axis=1)), np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {"format": LUT_FORMAT, "version": 1, "steps": self.steps,
                "frequencies": list(self.frequencies), "bins": int(self.error_rad.shape[1]),
                "error_rad": np.round(self.error_rad, 7).tolist()}

    @classmethod
    def from_dict(cls, data: Any) -> PhaseErrorLUT:
        """The table of :meth:`to_dict` (``ValueError`` naming the key when malformed)."""
        if not isinstance(data, dict) or data.get("format") != LUT_FORMAT:
            raise ValueError(f"format: not a phase-error table (expected \"{LUT_FORMAT}\")")
        if data.get("version") != 1:
            raise ValueError("version: unsupported phase-error table version "
                             f"{data.get('version')!r}")
        try:
            table = np.asarray(data["error_rad"], np.float64)
            steps = int(data.get("steps", 0))
            freqs = tuple(float(k) for k in data.get("frequencies", ()))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"error_rad: malformed phase-error table ({exc})") from None
        if table.ndim != 2 or table.shape[1] < 8 or not np.isfinite(table).all():
            raise ValueError("error_rad: expected a finite (K, bins >= 8) table, got shape "
                             f"{table.shape}")
        if freqs and len(freqs) != table.shape[0]:
            raise ValueError(f"frequencies: {len(freqs)} listed for a table of "
                             f"{table.shape[0]} rows")
        return cls(table, steps, freqs)

    @cached_property
    def series(self) -> PhaseErrorSeries | None:
        """The table as a short Fourier series (:func:`fit_series`) in the harmonics of its
        period 2π/N (N = :attr:`steps`), fitted once per table; None where the steps are not
        recorded or no series within :data:`SERIES_MAX_HARMONICS` harmonics reproduces the
        table to :data:`SERIES_MAX_DEV_RAD` (learned tables: their bins carry the learning's
        noise in every harmonic)."""
        return fit_series(self.error_rad, self.steps) if self.steps else None

    def kernel_table(self) -> npt.NDArray[np.float32]:
        """(K, bins + 2) float32 the table for the fused kernel: entry j of a row is the error at
        bin centre j − 1 taken circularly, so that :meth:`apply`'s interpolation between bins
        ``i`` and ``i + 1`` (i = −1 … bins − 1) needs no modulo."""
        e = self.error_rad
        return np.ascontiguousarray(np.concatenate([e[:, -1:], e, e[:, :1]], axis=1), np.float32)

    def digest(self) -> str:
        """sha256 of :meth:`to_dict`'s canonical JSON: names the table in options hashes."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    def __eq__(self, other: object) -> bool:  # by content (an array field has no plain ==)
        return isinstance(other, PhaseErrorLUT) and self.digest() == other.digest()

    def __hash__(self) -> int:
        return hash(self.digest())

    def apply(self, wrapped: npt.ArrayLike) -> F64:
        """Corrected wrapped phases: ``wrapped − error(wrapped)`` (linear interpolation,
        circular), in [0, 2π).

        Args:
            wrapped: (K, H, W) wrapped phases, radians, K = the table's frequencies.
        """
        w = np.asarray(wrapped, dtype=np.float64)
        k_n = self.error_rad.shape[0]
        if w.ndim != 3 or w.shape[0] != k_n:
            raise ValueError(f"wrapped: expected shape ({k_n}, H, W), got {w.shape}")
        out = np.empty_like(w)
        for k in range(k_n):
            corr = _interpolate(self.error_rad[k:k + 1], w[k])[0]
            out[k] = np.mod(w[k] - corr, TWO_PI)
        out[out >= TWO_PI] = 0.0
        return out
