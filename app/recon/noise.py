"""The camera's temporal noise from one fringe set: what the fringe model leaves unexplained.

With N > 3 phase steps the sinusoid ``A + B cos(φ + δ_n)`` leaves N − 3 degrees of freedom
per frequency and pixel. Their residual, regressed on the pixel's mean intensity over the
whole image (without the pixels that are not noise: a moving tool, glints;
:func:`_trimmed_fit`), gives the shot + read model ``σ_I² = read² + gain·I``
(:class:`~app.recon.sensor.SensorNoise`), which then gives every pixel its σ_I from its own
intensity.

A projector's gamma adds harmonics h of the fringe to every sample, ``B_h cos(h(φ + δ_n))``;
they are not noise. Those with h ≡ ±1 mod N alias onto the fundamental (the phase error a
table from ``fringescope gamma`` corrects); the others land in the residual. Two parts of
the fit take them out:

* per pixel, where the steps allow (N ≥ 8), harmonics 2 … H, H = ⌊(N − 4)/2⌋, keeping
  N − 1 − 2H ≥ 3 degrees of freedom (on the real CFPE captures, N = 12 and a home
  projector, this turns a residual "noise" of 4–8 DN at 10 DN into 0.7 DN);
* across the set, what is left of them (:func:`_harmonic_fit`). A projector's nonlinearity
  acting on its own pattern value makes each harmonic a fixed fraction of the pixel's
  fringe amplitude B whatever the albedo; a real one is not that clean (the CFPE home
  projector and 8-bit camera: the 3rd harmonic reaches −0.056 of B where B ≥ 100 DN while
  the 2nd falls), so the fractions are fitted as quadratic in the pixel's level. Residual harmonic
  ĥ (h ≡ ±ĥ mod N) is fitted as ``B·Σ_h (a_h cos hφ + b_h sin hφ)``, ``a_h = a_h0 +
  a_h1·t + a_h2·t²``, ``t = A/Ã − 1`` (A the level, Ã the set's median), the
  coefficients common to all pixels of a frequency — a few numbers for tens of thousands of
  pixels, so the noise keeps its degrees of freedom. For N = 4 (the paper's schedule) the
  one residual per frequency is the Nyquist component, ``B_2 cos 2φ + B_6 cos 6φ + …``: on
  a twin whose projector has gamma 1.5 a fit without it read 6.1 DN/e⁻ of "gain" (the
  sensor's is 0.016) and refused nearly every pixel; on the real CFPE 4-step subsets fixed
  fractions gave σ_I 1.57–5.48 × the 12-step fit's (scene 8: gain 3.1 DN/e⁻), the
  level-dependent ones 0.85–1.25 × (``benchmarks/bench_gamma_self.py``).

The residual is orthogonal to the fundamental whatever a phase-error table does to φ, so
the estimate is the same with and without one.

Cost: one pass over a regular subsample of the pixels (numba; integer samples, no float
copy of the frames), then the harmonic and the trimmed fits on that subsample.
:class:`NoiseFit` carries the estimate's standard error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.schedule import PatternSchedule
from app.recon.gamma import PhaseErrorLUT
from app.recon.gamma_model import self_calibrated_table
from app.recon.phase import check_stack
from app.recon.sensor import NoiseSource, SensorNoise

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: pixels the fit reads, about: every s-th row and column (the standard error this leaves
#: is printed by ``benchmarks/bench_noise.py``)
MAX_PIXELS = 20_000
#: the lowest fringe harmonics fitted across the set for each residual harmonic
SET_HARMONICS = 2
#: pixels per chunk of the harmonic fit (noise_kernels.CHUNK); every other chunk gives the
#: normal equations
FIT_CHUNK = 1024
#: ridge of the harmonic fit, relative to each regressor's sum of squares (+ 1: an all-dark
#: set stays solvable). Where the pixels' levels span little (a uniform scene) t and t² are
#: nearly collinear and their split is told apart by nothing but noise; the ridge keeps it
#: small instead of noise-driven (it shrinks only combinations of regressors whose share of
#: the sums of squares is below ρ), and it bounds the normal equations' condition, so the
#: kernel's sums in another order give the numpy solution to ~10⁻⁹
HARMONIC_RIDGE = 1e-6
#: the share of pixels whose trim changed (at first: beyond the 0.1 % that noise gives)
#: after which the set's harmonics are fitted again on the pixels kept
REFIT_SHARE = 0.01
#: at most this many refits of the set's harmonics
REFITS = 4
#: the noise of rounding to whole codes, DN (uniform over one code: 1/√12)
QUANTISATION_NOISE_DN = 1.0 / math.sqrt(12.0)
#: a pixel whose residual variance exceeds its model's by the χ²_ν/ν quantile of this
#: probability is not noise (a moving tool, a glint): left out of the fit
OUTLIER_QUANTILE = 0.999


@dataclass(frozen=True)
class NoiseFit:
    """A fitted noise model and its standard error.

    Attributes:
        noise: the model, clipped (gain ≥ 0, read noise ≥ :data:`QUANTISATION_NOISE_DN`).
        read_var_dn2, gain_dn_per_e: the fit ``σ_I² = read_var + gain·I`` (a negative
            gain refitted as 0 with read_var the mean; a negative read_var kept: see
            :func:`fit_sensor_noise`).
        cov: (2, 2) float64 covariance of (read_var DN², gain DN/e⁻): each kept pixel's
            residual variance is σ_I²·χ²_ν/ν, of variance 2σ_I⁴/ν, pixels independent.
        pixels: pixels in the final fit.
        dof: ν, the residual's degrees of freedom per pixel.
        steps: N, the set's phase steps per frequency.
        harmonics: (K, d, 2·S) float64, the projector harmonics common to the set at its
            median level (A = Ã): for frequency k and residual column j, the
            coefficients (a_h, b_h) of ``B cos hφ``, ``B sin hφ`` over h in ``sources[j]``,
            scaled to the column's basis (for N = 4 the one column is the Nyquist one and
            a_2 is the 2nd harmonic's fraction of the fringe amplitude B;
            :mod:`app.recon.gamma_model`).
        sources: (d, S) int64, the harmonics h of each residual column.
        harmonic_slopes: (K, d, 2, 2·S) float64, how those coefficients change with the
            pixel's level: the coefficients of t = A/Ã − 1 (index 0) and of t² (index 1).
        brightness_centre: (K,) float64, Ã per frequency, DN: the median level of the
            pixels the harmonics were fitted on.
        level_moments: (K, 2) float64, E[t] and E[t²] of t = A/Ã − 1 over those pixels
            (every :data:`CENTRE_EVERY`-th), weighted by B² (the regressors' weight in a
            least-squares fit).
    """

    noise: SensorNoise
    read_var_dn2: float
    gain_dn_per_e: float
    cov: F64
    pixels: int
    dof: int
    steps: int
    harmonics: F64
    sources: I64
    harmonic_slopes: F64
    brightness_centre: F64
    level_moments: F64

    @property
    def mean_harmonics(self) -> F64:
        """(K, d, 2·S) float64: the harmonics' B²-weighted mean share over the fitted
        pixels, ``a_h0 + a_h1·E[t] + a_h2·E[t²]`` (:attr:`level_moments`): what one share
        common to all pixels reads, and what the set's gamma table is made from (on the
        CFPE 4-step subsets its table leaves 0.475 of the systematic phase error on the 36
        cases' mean, the share at the median level's 0.502, a fixed-share fit's 0.479)."""
        slope, curve = self.harmonic_slopes[:, :, 0], self.harmonic_slopes[:, :, 1]
        mean_t = self.level_moments[:, 0, None, None]
        mean_t2 = self.level_moments[:, 1, None, None]
        return np.asarray(self.harmonics + slope * mean_t + curve * mean_t2, np.float64)

    @property
    def gain_se(self) -> float:
        """Standard error of the gain, DN/e⁻."""
        return math.sqrt(max(float(self.cov[1, 1]), 0.0))

    @property
    def read_var_se_dn2(self) -> float:
        """Standard error of read², DN²."""
        return math.sqrt(max(float(self.cov[0, 0]), 0.0))

    def variance_se_dn2(self, mean_dn: float) -> float:
        """Standard error of the fitted σ_I² at intensity ``mean_dn`` (DN), DN²."""
        x = np.array([1.0, float(mean_dn)])
        return math.sqrt(max(float(x @ self.cov @ x), 0.0))


def estimate_sensor_noise(frames: Any, schedule: PatternSchedule, *,
                          max_code: int | None = None) -> SensorNoise:
    """Shot + read noise of the camera from what the fringe model leaves in one set.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = ``schedule.n_frames``.
        schedule: the pattern schedule; needs ``steps`` N > 3.
        max_code: sensor maximum code (pixels reaching it are left out); None → dtype max.

    Returns:
        :class:`~app.recon.sensor.SensorNoise` (``fit_sensor_noise(...).noise``).

    Raises:
        ValueError: N = 3 (no residual), wrong frame count, or too few usable pixels.
    """
    return fit_sensor_noise(frames, schedule, max_code=max_code).noise


def fit_sensor_noise(frames: Any, schedule: PatternSchedule, *,
                     max_code: int | None = None) -> NoiseFit:
    """:func:`estimate_sensor_noise` with the fit's standard error (:class:`NoiseFit`)."""
    stack = check_stack(frames)
    n = schedule.steps
    if n <= 3:
        raise ValueError(f"schedule: the N-step residual needs N > 3 steps, got {n}")
    if stack.shape[0] != schedule.n_frames:
        raise ValueError(f"frames: schedule needs {schedule.n_frames} frames, got {stack.shape[0]}")
    top = int(max_code) if max_code is not None else int(np.iinfo(stack.dtype).max)
    h, w = stack.shape[1:]
    step = max(1, math.isqrt(max(1, h * w // MAX_PIXELS)))
    basis, sources = _bases(n)
    k_n = len(schedule.frequencies)
    rows, cols = -(-h // step), -(-w // step)
    intensity = np.empty((rows, cols))
    usable = np.empty((rows, cols), np.bool_)
    level = np.empty((k_n, rows, cols))
    phasor = np.empty((k_n, 2, rows, cols))
    resid = np.empty((k_n, basis.shape[1] - 2, rows, cols))
    _set_statistics(stack, step, n, basis, top, intensity, usable, level, phasor, resid)
    if usable.sum() < 100:
        raise ValueError("frames: fewer than 100 unsaturated, non-black pixels to "
                         "estimate the noise from")
    dof = k_n * (basis.shape[1] - 2)
    var = np.empty((rows, cols))
    design = np.empty((2, rows, cols))
    harmonics = np.empty((k_n, sources.shape[0], 3 * 2 * sources.shape[1]))
    centre = np.empty(k_n)
    _harmonic_fit(level, phasor, resid, basis, sources, usable, var, design, harmonics, centre)
    fitted = usable
    # var ≈ read²·a + gain·b (a = b/I = 1 where the harmonics are nil): the line through
    # (b/a, var/a) is the model in σ_I²(I) form, each y still model·χ²_ν/ν
    x, y = _line_form(var, design, usable)
    coef, keep = _trimmed_fit(x, y, dof, usable)
    # the harmonics again without the outliers, until the pixels they are fitted on settle:
    # a moving region that the first fit let in can carry the level terms (a tool at 5× the
    # median level has t² = 16), and what those terms leave decides the next trim
    fitted_keep = np.ones_like(keep)
    for _ in range(REFITS):
        if np.count_nonzero(keep != fitted_keep) < REFIT_SHARE * x.size:
            break
        fitted = np.zeros_like(usable)
        fitted[usable] = keep
        fitted_keep = keep
        _harmonic_fit(level, phasor, resid, basis, sources, fitted, var, design, harmonics,
                      centre)
        x, y = _line_form(var, design, usable)
        coef, keep = _trimmed_fit(x, y, dof, usable, start=coef)
    if coef[1] < 0.0:  # no shot noise: the level alone (a set of one level leaves it free)
        coef = np.array([float(y[keep].mean()), 0.0])
    coef = coef / _chi2_limit(dof)[2]
    cov = _covariance(x[keep], coef, dof)
    # a fit can reach 0 read noise (motion in the set inflates the shot-noise slope); no sensor
    # is below its rounding, and the motion test needs a read noise > 0. The slope is kept as
    # fitted: on a set that moves it is the steeper one, and the validity rule refuses more
    read_dn = max(math.sqrt(max(float(coef[0]), 0.0)), QUANTISATION_NOISE_DN)
    noise = SensorNoise(gain_dn_per_e=max(float(coef[1]), 0.0), read_noise_dn=read_dn)
    m = 2 * sources.shape[1]
    slopes = np.stack([harmonics[..., m:2 * m], harmonics[..., 2 * m:]], axis=2)
    return NoiseFit(noise, float(coef[0]), float(coef[1]), cov, int(keep.sum()), dof, n,
                    np.ascontiguousarray(harmonics[..., :m]), sources, slopes, centre,
                    _level_moments(level, phasor, fitted, centre))


@dataclass(frozen=True)
class SetNoise:
    """What a run without a given noise model takes from its own set.

    Attributes:
        noise: the camera noise: the set's fit, or :meth:`SensorNoise.typical`.
        source: ``"set"`` or ``"nominal"``.
        note: why the set could not give it ("" when it did).
        phase_error: the projector-gamma table the set's own 2nd harmonic gives under a
            power-law projector (:func:`app.recon.gamma_model.self_calibrated_table`; N = 4
            only), None otherwise.
    """

    noise: SensorNoise
    source: NoiseSource
    note: str
    phase_error: PhaseErrorLUT | None


def resolve_set_noise(frames: Any, schedule: PatternSchedule, max_code: int) -> SetNoise:
    """The noise model and gamma table a run without given ones uses: the set's own.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order.
        schedule: the set's pattern schedule.
        max_code: sensor maximum code of the set.

    Returns:
        :class:`SetNoise`: :func:`fit_sensor_noise` of the set where N > 3 and enough
        pixels are usable (with its power-law table where N = 4), else
        :meth:`SensorNoise.typical`, ``"nominal"`` and no table.
    """
    try:
        fit = fit_sensor_noise(frames, schedule, max_code=max_code)
    except ValueError as exc:  # N = 3 (no residual) or too few usable pixels
        return SetNoise(SensorNoise.typical(max_code), "nominal", str(exc), None)
    table = self_calibrated_table(fit.mean_harmonics, fit.sources, fit.steps)
    return SetNoise(fit.noise, "set", "", table)


def resolve_sensor_noise(frames: Any, schedule: PatternSchedule,
                         max_code: int) -> tuple[SensorNoise, NoiseSource, str]:
    """The noise model a run without a given one uses: the set's own where it has one.

    Returns:
        ``(noise, source, note)`` of :func:`resolve_set_noise`.
    """
    est = resolve_set_noise(frames, schedule, max_code)
    return est.noise, est.source, est.note


@lru_cache(maxsize=16)
def _bases(n: int) -> tuple[F64, I64]:
    """The N-step projections: (N, 2 + d) float64 columns cos δ, sin δ, then an orthonormal
    basis of the residual (the harmonics above H, H = max(1, ⌊(N − 4)/2⌋), d = N − 1 − 2H);
    and (d, :data:`SET_HARMONICS`) int64, the fringe harmonics h ≥ 2 that alias onto each
    residual column (h ≡ ±ĥ mod N, the lowest)."""
    delta = 2.0 * np.pi * np.arange(n) / n
    fitted = max(1, (n - 4) // 2)
    cols = [np.cos(delta), np.sin(delta)]
    sources: list[list[int]] = []
    for hh in range(fitted + 1, n // 2 + 1):
        alias = [h for h in range(2, hh + 2 * n * SET_HARMONICS) if h % n in (hh, n - hh)]
        if 2 * hh == n:  # the Nyquist harmonic: one real column
            cols.append(np.cos(hh * delta) / math.sqrt(n))
            sources.append(alias[:SET_HARMONICS])
        else:
            scale = math.sqrt(2.0 / n)
            cols += [scale * np.cos(hh * delta), scale * np.sin(hh * delta)]
            sources += [alias[:SET_HARMONICS]] * 2
    return np.stack(cols, axis=1), np.array(sources, np.int64)


def _set_statistics(stack: npt.NDArray[Any], step: int, n: int, basis: F64, top: int,
                    intensity: F64, usable: npt.NDArray[np.bool_], level: F64, phasor: F64,
                    resid: F64) -> None:
    """Fill the per-pixel statistics of the subsample (every ``step``-th row and column).

    Args:
        stack: (F, H, W) uint8/uint16 frames, F = K·N.
        step: subsample stride, px.
        n: N, steps per frequency.
        basis, top: :func:`_bases`'s first array; the sensor's maximum code.
        intensity: out (R, C) float64, mean over the frames, DN.
        usable: out (R, C) bool, no sample at 0 or ``top``.
        level: out (K, R, C) float64, mean over each frequency's N frames, DN.
        phasor: out (K, 2, R, C) float64, Σ I cos δ and Σ I sin δ per frequency, DN.
        resid: out (K, d, R, C) float64, the residual's orthonormal coordinates, DN.
    """
    if _nb is None:
        _statistics_numpy(stack, step, n, basis, top, intensity, usable, level, phasor, resid)
    else:
        _nb.set_statistics(stack, step, n, basis, top, intensity, usable, level, phasor, resid)


def _statistics_numpy(stack: npt.NDArray[Any], step: int, n: int, basis: F64, top: int,
                      intensity: F64, usable: npt.NDArray[np.bool_], level: F64, phasor: F64,
                      resid: F64) -> None:
    """:func:`_set_statistics` in numpy (without numba; the kernel's test oracle)."""
    sub = stack[:, ::step, ::step]
    k_n = sub.shape[0] // n
    blocks = sub.reshape(k_n, n, *sub.shape[1:]).astype(np.float64)
    level[...] = blocks.mean(axis=1)
    proj = np.einsum("knrc,nj->kjrc", blocks, basis)
    phasor[...] = proj[:, :2]
    resid[...] = proj[:, 2:]
    intensity[...] = sub.mean(axis=0)
    usable[...] = (sub.max(axis=0) < top) & (sub.min(axis=0) > 0)


#: the harmonics' centre Ã is the median level of every this-th pixel of the fit's mask (a
#: centre needs no more; the median of all costs 1.2 ms CPU of the fit's 9 on a 1384 × 1032
#: set)
CENTRE_EVERY = 4


def _level_moments(level: F64, phasor: F64, mask: npt.NDArray[np.bool_], centre: F64) -> F64:
    """(K, 2) float64: E[t], E[t²] of t = A/Ã − 1 over every :data:`CENTRE_EVERY`-th
    ``mask`` pixel (as :func:`brightness_centre`) weighted by |phasor|² ∝ B² (0 where the
    mask holds no light).

    Args:
        level: (K, R, C) DN; phasor: (K, 2, R, C) DN; mask: (R, C) bool; centre: (K,) Ã, DN.
    """
    k_n = level.shape[0]
    picks = np.flatnonzero(mask)[::CENTRE_EVERY]
    flat = phasor.reshape(k_n, 2, -1)
    weight = flat[:, 0, picks] ** 2 + flat[:, 1, picks] ** 2  # (K, P)
    t = level.reshape(k_n, -1)[:, picks] / centre[:, None] - 1.0
    total = np.maximum(weight.sum(axis=1), np.finfo(np.float64).tiny)
    wt = weight * t
    return np.stack([wt.sum(axis=1) / total, (wt * t).sum(axis=1) / total], axis=1)


def brightness_centre(level: F64, mask: npt.NDArray[np.bool_]) -> F64:
    """(K,) float64: each frequency's median level Ã (DN) over every
    :data:`CENTRE_EVERY`-th pixel of the ``mask`` (row-major), where the set's harmonics are
    centred (1.0 where the mask is empty or dark: the brightness terms are then nil, not
    undefined).

    Args:
        level: (K, R, C) each frequency's mean, DN.
        mask: (R, C) bool.
    """
    picks = np.flatnonzero(mask)[::CENTRE_EVERY]
    if picks.size == 0:
        return np.ones(level.shape[0])
    centre = np.median(level.reshape(level.shape[0], -1)[:, picks], axis=1)
    return np.asarray(np.where(centre > 0.0, centre, 1.0), np.float64)


def _harmonic_fit(level: F64, phasor: F64, resid: F64, basis: F64, sources: I64,
                  mask: npt.NDArray[np.bool_], var: F64, design: F64, coef: F64,
                  centre: F64) -> None:
    """Residual variance per pixel after the fringe harmonics common to the set.

    For each frequency k and residual column j, ``resid[k, j] ≈ M = Σ_h a_h·B cos hφ +
    b_h·B sin hφ`` over h in ``sources[j]`` (B = |phasor|, φ its angle), where each
    coefficient is quadratic in the pixel's level: ``a_h = a_h0 + a_h1·t + a_h2·t²``,
    ``t = A/Ã − 1`` (A the frequency's mean level, Ã the mask's median:
    :func:`brightness_centre`), so (a_h0, b_h0) are the harmonic at the median level. A
    projector's nonlinearity alone gives fixed fractions of B; the real CFPE camera +
    projector's harmonics change with brightness (the 3rd harmonic reaches −0.056 of B
    where B ≥ 100 DN while the 2nd falls), and a fixed fraction left them in the residual
    (``benchmarks/bench_gamma_self.py``). The level, not the amplitude, is the regressor: with
    N = 4 the decoded |z| carries the aliased 3rd and 5th harmonics as a cos 4φ ripple, and
    |z|·cos 2φ regressors then trade with the fixed ones (on a γ 1.5 twin the fit read a
    2nd harmonic 5 % off and a noise 6 % high); the level's ripple is the 4th harmonic's,
    ~0.3 % of B. The 3·2·|sources| coefficients per (k, j), least squares over the ``mask``
    pixels of every other chunk of :data:`FIT_CHUNK`, are a few numbers against thousands
    of pixels: the residual of the pixels they are fitted on is smaller by their leverage
    (m/P on average), that of the pixels between them larger by about as much, so ``var``
    (R, C), the mean square of what is left (DN²), keeps K·d degrees of freedom per pixel.

    M is computed from the pixel's own phasor and level, whose noise is correlated with the
    residual's where the samples' shot noise differs (σ_n² = read² + gain·I_n): the
    residual's noise is ``Σ_n w_n ε_n``, ``w_n = q_jn − (∂M/∂C) cos δ_n − (∂M/∂S) sin δ_n −
    (∂M/∂A)/N``, of variance ``read²·Σ w_n² + gain·Σ w_n² I_n``. ``design`` (2, R, C) gets
    those two sums, averaged as ``var`` (1 and the pixel's level where M is nil): the fit's
    regressors.

    Args:
        level: (K, R, C) each frequency's mean, DN; phasor (K, 2, R, C) and resid
            (K, d, R, C) as :func:`_set_statistics` fills them; basis, sources from
            :func:`_bases`.
        mask: (R, C) bool, the pixels to fit the harmonics on.
        var, design: out, (R, C) and (2, R, C) float64.
        coef: out, (K, d, 3·2·S) float64 (S = :data:`SET_HARMONICS`): per frequency and
            residual column the (a_h, b_h) over h in ``sources[j]`` at the median level
            (fractions of B), then their coefficients of t, then of t².
        centre: out, (K,) float64, :func:`brightness_centre` of the mask (Ã, DN).
    """
    centre[...] = brightness_centre(level, mask)
    if _nb is None:
        _harmonic_fit_numpy(level, phasor, resid, basis, sources, centre, mask, var, design,
                            coef)
    else:
        _nb.harmonic_fit(level, phasor, resid, basis, _moments(basis), sources, centre,
                         HARMONIC_RIDGE, mask, var, design, coef)


def _harmonic_fit_numpy(level: F64, phasor: F64, resid: F64, basis: F64, sources: I64,
                        centre: F64, mask: npt.NDArray[np.bool_], var: F64, design: F64,
                        coef_out: F64) -> None:
    """:func:`_harmonic_fit` in numpy (``centre`` given)."""
    z = phasor[:, 0] + 1j * phasor[:, 1]  # (K, R, C)
    mag = np.abs(z)
    unit = np.where(mag > 0, z / np.where(mag > 0, mag, 1.0), 1.0)
    k_n, d = resid.shape[:2]
    n = basis.shape[0]
    # the normal equations from every other chunk of FIT_CHUNK pixels, as the kernel
    every = (np.arange(mask.size) // FIT_CHUNK) % 2 == 0
    mask = mask & every.reshape(mask.shape)
    var[...] = 0.0
    design[...] = 0.0
    for k in range(k_n):
        samples = (level[k][None] + (2.0 / n) * np.einsum("n,rc->nrc", basis[:, 0], phasor[k, 0])
                   + (2.0 / n) * np.einsum("n,rc->nrc", basis[:, 1], phasor[k, 1])
                   + np.einsum("nj,jrc->nrc", basis[:, 2:], resid[k]))
        t = level[k] / centre[k] - 1.0
        for j in range(d):
            terms = [mag[k] * unit[k] ** h for h in sources[j]]
            base = [f(v) for v in terms for f in (np.real, np.imag)]
            x = np.stack(base + [c * t for c in base] + [c * t * t for c in base], axis=-1)
            # the ridge-regularised least squares as augmented rows, solved by lstsq (the
            # kernel solves its normal equations: an independent route to the same solution)
            fitted = x[mask]
            ridge = np.diag(np.sqrt(HARMONIC_RIDGE * ((fitted**2).sum(axis=0) + 1.0)))
            coef = np.linalg.lstsq(np.concatenate([fitted, ridge]),
                                   np.concatenate([resid[k, j][mask], np.zeros(x.shape[-1])]),
                                   rcond=None)[0]
            coef_out[k, j] = coef
            var += (resid[k, j] - x @ coef) ** 2
            # γ = a − i·b per source: at the median level, and its coefficients of t and t²
            g0, g1, g2 = (coef[o:o + len(base):2] - 1j * coef[o + 1:o + len(base):2]
                          for o in (0, len(base), 2 * len(base)))
            g_z = np.zeros_like(z[k])
            g_zb = np.zeros_like(z[k])
            d_level = np.zeros_like(mag[k])
            for i, h in enumerate(sources[j]):
                g = g0[i] + (g1[i] + g2[i] * t) * t
                g_z += (1 + h) / 2 * g * unit[k] ** (h - 1)
                g_zb += (1 - h) / 2 * g * unit[k] ** (h + 1)
                d_level += np.real((g1[i] + 2.0 * g2[i] * t) * unit[k] ** h) * mag[k] / centre[k]
            alpha, beta = np.real(g_z + g_zb), -np.imag(g_z - g_zb)
            w = (basis[:, 2 + j, None, None] - alpha[None] * basis[:, 0, None, None]
                 - beta[None] * basis[:, 1, None, None] - d_level[None] / n)
            design[0] += (w**2).sum(axis=0)
            design[1] += (w**2 * samples).sum(axis=0)
    var /= k_n * d
    design /= k_n * d


@lru_cache(maxsize=16)
def _moment_table(n: int) -> F64:
    """:func:`_moments` of the N-step basis (cached)."""
    return _moments_of(_bases(n)[0])


def _moments(basis: F64) -> F64:
    """(d, 6, 3 + d) float64: for residual column j and the pairs (e_u, e_v) = (q_j, q_j),
    (q_j, cos δ), (q_j, sin δ), (cos δ, cos δ), (sin δ, sin δ), (cos δ, sin δ), the sums
    Σ_n e_u e_v f_n over the sample's terms f = 1, cos δ, sin δ, q_1 … q_d."""
    return _moment_table(basis.shape[0])


def _moments_of(basis: F64) -> F64:
    d = basis.shape[1] - 2
    ones = np.ones(basis.shape[0])
    terms = np.stack([ones, basis[:, 0], basis[:, 1], *basis[:, 2:].T])  # (3 + d, N)
    out = np.empty((d, 6, 3 + d))
    for j in range(d):
        q, c, s = basis[:, 2 + j], basis[:, 0], basis[:, 1]
        for t, (u, v) in enumerate(((q, q), (q, c), (q, s), (c, c), (s, s), (c, s))):
            out[j, t] = terms @ (u * v)
    return out


def _line_form(var: F64, design: F64, usable: npt.NDArray[np.bool_]) -> tuple[F64, F64]:
    """(x, y) = (b/a, var/a) of the usable pixels: ``y ≈ read² + gain·x``."""
    a = design[0][usable]
    return design[1][usable] / a, var[usable] / a


@lru_cache(maxsize=64)
def _chi2_limit(dof: int) -> tuple[float, float, float]:
    """(χ²_ν/ν quantile :data:`OUTLIER_QUANTILE`, χ²_ν/ν median, mean of χ²_ν/ν below that
    quantile) for ν = ``dof``: the trim's bias, E[χ²_ν; χ²_ν < c] = ν·F_{ν+2}(c)."""
    from scipy.stats import chi2

    c = float(chi2.ppf(OUTLIER_QUANTILE, dof))
    kept = float(chi2.cdf(c, dof + 2)) / OUTLIER_QUANTILE
    return c / dof, float(chi2.median(dof)) / dof, kept


#: pixels the trimmed fit's robust start reads at most (medians of intensity bins)
START_PIXELS = 8192
#: side of the square blocks of the subsample (in subsample pixels) in which outliers are
#: counted: a moving tool or a glint is a region, noise's outliers are scattered
OUTLIER_BLOCK = 8
#: a block holding more than this share of outliers is left out whole (noise alone puts
#: 1 − :data:`OUTLIER_QUANTILE` = 0.1 % in each; 4 of 64 has probability ~6·10⁻⁷)
OUTLIER_BLOCK_SHARE = 0.05


def _trimmed_fit(intensity: F64, var: F64, dof: int, grid: npt.NDArray[np.bool_] | None = None,
                 start: F64 | None = None) -> tuple[F64, npt.NDArray[np.bool_]]:
    """``(read², gain)`` of ``var ≈ read² + gain·intensity`` without the pixels that are not noise.

    Where the scene holds still a pixel's residual variance is σ_I²·χ²_ν/ν (ν = ``dof``).
    A moving tool or a specular glint makes it orders of magnitude larger in a few pixels,
    and those few would carry a least-squares fit (on a twin anastomosis: 5 % of the pixels,
    96 % of the residual, the gain 58× the sensor's). The fit is therefore repeated on the
    pixels within the χ²_ν/ν quantile :data:`OUTLIER_QUANTILE` of the model so far, until
    the kept set settles (the trim removes 0.1 % of true noise: a bias below 1 %).

    Two things keep a large moving region from carrying the fit (the twin anastomosis
    at half the LED current: forceps over 15 % of the view, the brightest pixels nearly
    all on them; the start's line through the bins' medians then fell below zero for
    every pixel dimmer than the forceps, the trim kept only the 1,500 brightest pixels and
    read a gain 56× the sensor's):

    * the start is the repeated-median line (Siegel; ``scipy.stats.siegelslopes``)
      through the bins' medians, which a minority of bins, however far off, cannot tilt;
    * the model the trim compares with is never below the rounding's variance, and where
      ``grid`` is given, a block of :data:`OUTLIER_BLOCK` × :data:`OUTLIER_BLOCK` pixels
      holding more than :data:`OUTLIER_BLOCK_SHARE` outliers is left out whole: a moving
      region's pixels whose residual happens to stay under the limit are its edges and
      slow parts, not noise (whether a pixel goes depends on its neighbours, which are
      independent of its own noise, so this leaves the kept pixels' χ² unbiased).

    Args:
        intensity, var: (P,) float64 mean intensity (DN) and residual variance (DN²).
        dof: ν, the residual's degrees of freedom per pixel.
        grid: (R, C) bool with P true values, where the P pixels sit in the subsample
            (row-major); None: no blocks.
        start: (2,) a model to start from; None: the repeated-median line through the
            medians of equal-count intensity bins of at most :data:`START_PIXELS` pixels
            (χ²_ν/ν's median divided out).

    Returns:
        ``(coef, keep)``: (2,) float64 read noise variance, DN², and gain, DN per electron
        (either may be negative; the caller clips), and (P,) bool the pixels fitted.
    """
    limit, median, _ = _chi2_limit(dof)
    if start is None:
        every = max(1, intensity.size // START_PIXELS)
        xs, vs = intensity[::every], var[::every]
        bins = np.array_split(np.argsort(xs, kind="stable"), max(2, min(32, xs.size // 50)))
        med = np.array([np.median(vs[b]) for b in bins]) / median
        centre = np.array([xs[b].mean() for b in bins])
        coef = _repeated_median_line(centre, med)
    else:
        coef = np.asarray(start, np.float64)
    floor = QUANTISATION_NOISE_DN**2
    blocks = None if grid is None else _block_layout(grid)  # fixed by the grid: once per fit
    keep = np.zeros(intensity.size, bool)
    for _ in range(20):
        new = var <= limit * np.maximum(coef[0] + coef[1] * intensity, floor)
        if blocks is not None:
            new &= ~_clustered(~new, *blocks)
        if new.sum() < 100 or np.array_equal(new, keep):
            break
        keep = new
        coef = _line(intensity[keep], var[keep])
    if not keep.any():
        keep = np.ones(intensity.size, bool)
        coef = _line(intensity, var)
    return coef, keep


def _repeated_median_line(x: F64, y: F64) -> F64:
    """(intercept, slope) of Siegel's repeated-median line through (x, y) (breakdown 50 %)."""
    if np.ptp(x) <= 0.0:  # one level: no slope to tell
        return np.array([float(np.median(y)), 0.0])
    from scipy.stats import siegelslopes

    fit = siegelslopes(y, x)
    return np.array([float(fit.intercept), float(fit.slope)])


def _block_layout(grid: npt.NDArray[np.bool_]) -> tuple[I64, I64]:
    """For the P true pixels of ``grid`` (R, C), row-major: (P,) int64 the index of each one's
    :data:`OUTLIER_BLOCK`-square block, and (blocks,) int64 how many grid pixels each holds."""
    rows, cols = grid.shape
    b = OUTLIER_BLOCK
    per_row = -(-cols // b)
    block_of = ((np.arange(rows)[:, None] // b) * per_row + np.arange(cols)[None, :] // b)[grid]
    count = np.bincount(block_of, minlength=-(-rows // b) * per_row)
    return block_of.astype(np.int64), count.astype(np.int64)


def _clustered(outlier: npt.NDArray[np.bool_], block_of: I64,
               count: I64) -> npt.NDArray[np.bool_]:
    """(P,) bool: the pixels in blocks (:func:`_block_layout`) whose share of ``outlier`` (P,)
    among the block's pixels exceeds :data:`OUTLIER_BLOCK_SHARE`."""
    bad = np.bincount(block_of, weights=outlier.astype(np.float64), minlength=count.size)
    share = bad / np.maximum(count, 1)
    return np.asarray(share[block_of] > OUTLIER_BLOCK_SHARE, np.bool_)


def _line(x: F64, y: F64) -> F64:
    """(intercept, slope) of the least-squares line through (x, y) (closed form)."""
    xm, ym = float(x.mean()), float(y.mean())
    dx = x - xm
    sxx = float(dx @ dx)
    slope = float(dx @ (y - ym)) / sxx if sxx > 0 else 0.0
    return np.array([ym - slope * xm, slope])


def _covariance(x: F64, coef: F64, dof: int) -> F64:
    """(2, 2) covariance of the least-squares line's (intercept, slope) when each y is
    model(x)·χ²_ν/ν, of variance 2·model²/ν (the sandwich formula, pixels independent)."""
    w = 2.0 * np.maximum(coef[0] + coef[1] * x, 0.0) ** 2 / dof
    xx = x * x
    bread = np.linalg.inv(np.array([[x.size, x.sum()], [x.sum(), xx.sum()]]))
    wx = w * x
    meat = np.array([[w.sum(), wx.sum()], [wx.sum(), float(wx @ x)]])
    return np.asarray(bread @ meat @ bread, np.float64)


_nb: ModuleType | None
try:
    from app.recon import noise_kernels as _nb
except ImportError:  # numba missing: the numpy versions (slower, same results)
    _nb = None
