"""Wrapped phase, modulation, background and saturation of N-step fringe images.

For frames ``I_n = A + B cos(φ + δ_n)``, ``δ_n = 2π n / N`` (the projected pattern is
``0.5 + 0.5 cos(2π k x / w + δ_n)``), the N-step estimates are

    φ_w = atan2(−Σ I_n sin δ_n, Σ I_n cos δ_n)      (= 2π k x / w mod 2π)
    B   = (2 / N) · |Σ I_n e^{iδ_n}|
    A   = mean(I_n)

Phases are returned in ``[0, 2π)`` so that the k = 1 phase is directly the absolute
projector coordinate ``2π x / w``.

Saturation: where some samples of a frequency are clipped (at or above ``max_code``),
A, B and φ come from a least-squares fit of ``A + a cos δ_n + b sin δ_n`` to the
unclipped samples (φ = atan2(−b, a), B = |(a, b)|) while at least three remain; three
samples determine the three unknowns exactly, so one clipped shift of four costs only
noise. Only pixels with fewer than three unclipped samples in some frequency are
saturated.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

_nstep_kernel: Callable[..., None] | None
try:  # one compiled pass; numpy (the same values within a few ulps) where numba is missing
    from app.recon.phase_kernels import nstep_estimates as _nstep_kernel
except ImportError:
    _nstep_kernel = None

TWO_PI = 2.0 * math.pi
#: Least modulation B of the default (noise-aware) rule, codes: see :mod:`app.recon.validity`
#: (2 codes, less a margin that keeps the threshold off the lattice of integer frames' N-step
#: sums, where float64 and float32 would round a tie differently).
MODULATION_FLOOR_DN = 1.95

F64 = npt.NDArray[np.float64]


def default_max_code(dtype: Any) -> int:
    """Sensor maximum code for a frame dtype: 255 for uint8, 65535 for uint16.

    Cameras that deliver 10/12-bit data in uint16 frames need an explicit
    ``max_code`` (1023/4095) for saturation and the default modulation threshold.
    """
    dt = np.dtype(dtype)
    if dt == np.uint8:
        return 255
    if dt == np.uint16:
        return 65535
    raise ValueError(f"frames: dtype must be uint8 or uint16, got {dt}")


def resolve_levels(dtype: Any, max_code: int | None,
                   min_modulation: float | None) -> tuple[int, float]:
    """Validated ``(max_code, min_modulation)`` for frames of ``dtype``.

    ``max_code`` None → :func:`default_max_code`; ``min_modulation`` None →
    :data:`MODULATION_FLOOR_DN`, the floor of the noise-aware rule (the per-pixel threshold
    from the schedule and the sensor noise, :mod:`app.recon.validity`, applies on top of it;
    an explicit value replaces the rule).
    """
    top = default_max_code(dtype)
    if max_code is None:
        max_code = top
    if int(max_code) != max_code or not 1 <= max_code <= top:
        raise ValueError(f"max_code: must be an integer in 1..{top} for {np.dtype(dtype)} "
                         f"frames, got {max_code}")
    if min_modulation is None:
        min_modulation = MODULATION_FLOOR_DN
    if not (math.isfinite(min_modulation) and min_modulation >= 0.0):
        raise ValueError(f"min_modulation: must be finite and >= 0, got {min_modulation}")
    return int(max_code), float(min_modulation)


def check_stack(frames: Any, name: str = "frames") -> npt.NDArray[Any]:
    """Return ``frames`` as one (F, H, W) uint8/uint16 array; ``ValueError`` naming ``name``.

    A list/tuple of equal 2-D frames of one dtype is stacked.
    """
    if isinstance(frames, list | tuple):
        if not frames:
            raise ValueError(f"{name}: empty sequence")
        arrs = [np.asarray(f) for f in frames]
        dtypes = sorted({str(a.dtype) for a in arrs})
        if len(dtypes) > 1:
            raise ValueError(f"{name}: mixed dtypes {dtypes}")
        shapes = {a.shape for a in arrs}
        if len(shapes) > 1:
            raise ValueError(f"{name}: frames differ in shape {sorted(shapes)}")
        frames = np.stack(arrs)
    if not isinstance(frames, np.ndarray):
        raise ValueError(f"{name}: expected a numpy array, got {type(frames).__name__}")
    if frames.ndim != 3:
        raise ValueError(f"{name}: expected shape (F, H, W), got {frames.shape}")
    if frames.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{name}: dtype must be uint8 or uint16, got {frames.dtype}")
    if min(frames.shape) < 1:
        raise ValueError(f"{name}: empty array of shape {frames.shape}")
    return frames


@dataclass(frozen=True)
class WrappedPhase:
    """Per-frequency N-step estimates.

    Attributes:
        phase: (K, H, W) float64 wrapped phase in [0, 2π), radians.
        modulation: (K, H, W) float64 B, sensor codes.
        background: (H, W) float64 A averaged over all frames, codes.
        saturated: (H, W) bool, fewer than three samples below ``max_code`` in some frequency.
        recovered: (H, W) bool, some sample clipped but every frequency fitted from the rest.
    """

    phase: F64
    modulation: F64
    background: F64
    saturated: npt.NDArray[np.bool_]
    recovered: npt.NDArray[np.bool_] | None = None


def fit_unclipped(samples: npt.ArrayLike, ok: npt.ArrayLike,
                  delta: npt.ArrayLike) -> tuple[F64, F64]:
    """Least-squares ``I_n = A + a cos δ_n + b sin δ_n`` over the samples with ``ok``.

    Args:
        samples: (P, N) intensities, codes.
        ok: (P, N) bool, the samples to use (at least three per row).
        delta: (N,) phase shifts, radians.

    Returns:
        ``(phase, modulation)``: (P,) wrapped φ = atan2(−b, a) in [0, 2π), rad, and
        B = hypot(a, b), codes.
    """
    i = np.asarray(samples, dtype=np.float64)
    m = np.asarray(ok, dtype=np.float64)
    d = np.asarray(delta, dtype=np.float64)
    basis = np.stack([np.ones_like(d), np.cos(d), np.sin(d)])  # (3, N)
    normal = np.einsum("pn,in,jn->pij", m, basis, basis)
    rhs = np.einsum("pn,pn,in->pi", m, i, basis)
    coef = np.linalg.solve(normal, rhs[..., None])[..., 0]
    phase = np.mod(np.arctan2(-coef[:, 2], coef[:, 1]), TWO_PI)
    phase[phase >= TWO_PI] = 0.0
    return phase, np.hypot(coef[:, 1], coef[:, 2])


_Estimates = tuple[F64, F64, F64, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]


def nstep_estimates(frames: npt.NDArray[Any], steps: int, max_code: int) -> _Estimates:
    """:func:`nstep_estimates_numpy` by the compiled pass (:mod:`app.recon.phase_kernels`),
    or by numpy where numba is missing."""
    if _nstep_kernel is None:
        return nstep_estimates_numpy(frames, steps, max_code)
    n_freq, shape = frames.shape[0] // steps, frames.shape[1:]
    delta = TWO_PI * np.arange(steps) / steps
    phase, modulation = np.empty((n_freq, *shape)), np.empty((n_freq, *shape))
    background = np.empty(shape)
    saturated, recovered = np.empty(shape, np.bool_), np.empty(shape, np.bool_)
    _nstep_kernel(frames, steps, np.cos(delta), np.sin(delta), max_code, phase, modulation,
                  background, saturated, recovered)
    return phase, modulation, background, saturated, recovered


def nstep_estimates_numpy(frames: npt.NDArray[Any], steps: int, max_code: int) -> _Estimates:
    """Every frequency's N-step estimates before the clipped samples' refit, in numpy.

    Args:
        frames: (K·N, H, W) uint8/uint16, frequency-major, shift-minor.
        steps: N ≥ 3.
        max_code: samples at or above it are clipped.

    Returns:
        ``(phase, modulation, background, saturated, recovered)``: (K, H, W) float64 φ in
        [0, 2π), rad, and B, codes; (H, W) float64 mean of every frame, codes; (H, W) bool
        fewer than three unclipped samples in some frequency; (H, W) bool some sample clipped
        but not saturated. The compiled pass, used where numba is installed, gives the same
        within a few ulps (its atan2 is libm's, numpy's a SIMD one; BLAS sums in its order).
    """
    n_freq = frames.shape[0] // steps
    delta = TWO_PI * np.arange(steps) / steps
    cos_d, sin_d = np.cos(delta), np.sin(delta)
    shape = (n_freq, *frames.shape[1:])
    phase = np.empty(shape)
    modulation = np.empty(shape)
    total = np.zeros(frames.shape[1:])
    clipped = np.zeros(shape, np.int32)
    for k in range(n_freq):
        stack = frames[k * steps : (k + 1) * steps].astype(np.float64)
        s = np.tensordot(sin_d, stack, axes=1)
        c = np.tensordot(cos_d, stack, axes=1)
        phase[k] = np.mod(np.arctan2(-s, c), TWO_PI)
        modulation[k] = (2.0 / steps) * np.hypot(s, c)
        total += stack.sum(axis=0)
        clipped[k] = (frames[k * steps : (k + 1) * steps] >= max_code).sum(axis=0)
    # np.mod can return exactly 2π for tiny negative inputs; keep the half-open range.
    phase[phase >= TWO_PI] = 0.0
    saturated: npt.NDArray[np.bool_] = np.asarray((clipped > steps - 3).any(axis=0))
    recovered: npt.NDArray[np.bool_] = np.asarray((clipped > 0).any(axis=0) & ~saturated)
    return phase, modulation, total / frames.shape[0], saturated, recovered


def wrapped_phase(frames: Any, steps: int, *, max_code: int | None = None) -> WrappedPhase:
    """N-step wrapped phase of every frequency in a stack (float64, the oracle path).

    Args:
        frames: (K·N, H, W) uint8/uint16, frequency-major, shift-minor.
        steps: N ≥ 3 phase shifts per frequency.
        max_code: saturation code (default 255 / 65535 by dtype); clipped samples are
            left out of the fit (see the module docstring).

    Returns:
        :class:`WrappedPhase`.
    """
    frames = check_stack(frames)
    if int(steps) != steps or steps < 3:
        raise ValueError(f"steps: need an integer N >= 3, got {steps}")
    if frames.shape[0] % steps:
        raise ValueError(f"frames: {frames.shape[0]} frames is not a multiple of steps={steps}")
    max_code, _ = resolve_levels(frames.dtype, max_code, 0.0)
    n_freq = frames.shape[0] // steps
    delta = TWO_PI * np.arange(steps) / steps
    phase, modulation, background, saturated, recovered = nstep_estimates(
        np.ascontiguousarray(frames), steps, max_code)
    vv, uu = np.nonzero(recovered)
    for k in range(n_freq):
        samples = frames[k * steps : (k + 1) * steps, vv, uu].T  # (P, N)
        some = (samples >= max_code).any(axis=1)
        if some.any():
            phase[k, vv[some], uu[some]], modulation[k, vv[some], uu[some]] = fit_unclipped(
                samples[some], samples[some] < max_code, delta)
    return WrappedPhase(phase, modulation, background, saturated, recovered)
