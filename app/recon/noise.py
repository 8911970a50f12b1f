"""The camera's temporal noise from one fringe set: the residual of the N-step fit.

With N > 3 phase steps the sinusoid ``A + B cos(φ + δ_n)`` leaves N − 3 degrees of freedom
per frequency and pixel; their residual sum of squares estimates σ_I² there. Regressing
it on the pixel's mean intensity over the whole image (without the pixels that are not
noise: a moving tool, glints; :func:`_trimmed_fit`) gives the shot + read model
``σ_I² = read² + gain·I`` (:class:`~app.recon.reconstructor.SensorNoise`), which then
gives every pixel its σ_I from its own intensity.

A real projector's gamma adds harmonics of the fringe to every sample; they are not
noise but land in that residual. Where the steps allow (N ≥ 8) the fit therefore also
takes harmonics 2 … H, H = ⌊(N − 4)/2⌋, keeping N − 1 − 2H ≥ 3 degrees of freedom. On
the real CFPE captures (N = 12, a home projector) this turns a residual "noise" of 4–8 DN
at 10 DN into 0.7 DN. For N < 8 the estimate includes the second harmonic (for N = 4 it
is the whole residual): on a real projector it is an upper bound.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.schedule import PatternSchedule
from app.recon.phase import check_stack
from app.recon.sensor import NoiseSource, SensorNoise

MAX_PIXELS = 100_000  # a regular subsample is plenty for two parameters
MAX_FIT_PIXELS = 50_000  # of which the trimmed fit takes at most these


def estimate_sensor_noise(frames: Any, schedule: PatternSchedule, *,
                          max_code: int | None = None) -> SensorNoise:
    """Shot + read noise of the camera from the N-step fit residual of one fringe set.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = ``schedule.n_frames``.
        schedule: the pattern schedule; needs ``steps`` N > 3.
        max_code: sensor maximum code (pixels reaching it are left out); None → dtype max.

    Returns:
        :class:`~app.recon.reconstructor.SensorNoise` fitted to the residual variance
        against mean intensity (gain clipped at 0, read noise at least
        :data:`QUANTISATION_NOISE_DN`).

    Raises:
        ValueError: N = 3 (no residual), wrong frame count, or too few usable pixels.
    """
    stack = check_stack(frames)
    n = schedule.steps
    if n <= 3:
        raise ValueError(f"schedule: the N-step residual needs N > 3 steps, got {n}")
    if stack.shape[0] != schedule.n_frames:
        raise ValueError(f"frames: schedule needs {schedule.n_frames} frames, got {stack.shape[0]}")
    top = int(max_code) if max_code is not None else int(np.iinfo(stack.dtype).max)
    h, w = stack.shape[1:]
    step = max(1, math.isqrt(max(1, h * w // MAX_PIXELS)))
    sub = stack[:, ::step, ::step].astype(np.float64)
    delta = 2.0 * np.pi * np.arange(n) / n
    harmonics = max(1, (n - 4) // 2)
    cos_sin = [f(h * delta) for h in range(1, harmonics + 1) for f in (np.cos, np.sin)]
    basis = np.stack([np.ones(n)] + cos_sin, 1)
    residual = np.eye(n) - basis @ np.linalg.pinv(basis)  # (N, N) projector onto the unfitted part
    dof = n - basis.shape[1]
    var_sum = np.zeros(sub.shape[1:])
    k = len(schedule.frequencies)
    for fi in range(k):
        block = sub[fi * n:(fi + 1) * n]
        var_sum += (np.tensordot(residual, block, axes=1) ** 2).sum(axis=0) / dof
    var = var_sum / k
    intensity = sub.mean(axis=0)
    usable = (sub.max(axis=0) < top) & (sub.min(axis=0) > 0)
    if usable.sum() < 100:
        raise ValueError("frames: fewer than 100 unsaturated, non-black pixels to "
                         "estimate the noise from")
    fit = max(1, int(usable.sum()) // MAX_FIT_PIXELS)  # a regular share of the usable pixels
    read_var, gain = _trimmed_fit(intensity[usable][::fit], var[usable][::fit], dof * k)
    # a fit can reach 0 read noise (motion in the set inflates the shot-noise slope); no sensor
    # is below its rounding, and the motion test needs a read noise > 0
    read_dn = max(math.sqrt(max(float(read_var), 0.0)), QUANTISATION_NOISE_DN)
    return SensorNoise(gain_dn_per_e=max(float(gain), 0.0), read_noise_dn=read_dn)




#: the noise of rounding to whole codes, DN (uniform over one code: 1/√12)
QUANTISATION_NOISE_DN = 1.0 / math.sqrt(12.0)


def resolve_sensor_noise(frames: Any, schedule: PatternSchedule,
                         max_code: int) -> tuple[SensorNoise, NoiseSource, str]:
    """The noise model a run without a given one uses: the set's own where it has one.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order.
        schedule: the set's pattern schedule.
        max_code: sensor maximum code of the set.

    Returns:
        ``(noise, source, note)``: :func:`estimate_sensor_noise` of the set and ``"set"``
        where N > 3 and enough pixels are usable, else :meth:`SensorNoise.typical` and
        ``"nominal"``; ``note`` says why the set could not give it ("" when it did).
    """
    try:
        return estimate_sensor_noise(frames, schedule, max_code=max_code), "set", ""
    except ValueError as exc:  # N = 3 (no residual) or too few usable pixels
        return SensorNoise.typical(max_code), "nominal", str(exc)


#: a pixel whose residual variance exceeds its model's by the χ²_ν/ν quantile of this
#: probability is not noise (a moving tool, a glint): left out of the fit
OUTLIER_QUANTILE = 0.999


def _trimmed_fit(intensity: npt.NDArray[np.float64], var: npt.NDArray[np.float64],
                 dof: int) -> tuple[float, float]:
    """``(read², gain)`` of ``var ≈ read² + gain·intensity`` without the pixels that are not noise.

    Where the scene holds still a pixel's residual variance is σ_I²·χ²_ν/ν (ν = ``dof``).
    A moving tool or a specular glint makes it orders of magnitude larger in a few pixels,
    and those few would carry a least-squares fit (on a twin anastomosis: 5 % of the pixels,
    96 % of the residual, the gain 58× the sensor's). The fit is therefore repeated on the
    pixels within the χ²_ν/ν quantile :data:`OUTLIER_QUANTILE` of the model so far, until
    the kept set settles (the trim removes 0.1 % of true noise: a bias below 1 %).

    Args:
        intensity, var: (P,) float64 mean intensity (DN) and residual variance (DN²).
        dof: ν, the residual's degrees of freedom per pixel.

    Returns:
        read noise variance, DN², and gain, DN per electron (either may be negative; the
        caller clips).
    """
    from scipy.stats import chi2

    limit = float(chi2.ppf(OUTLIER_QUANTILE, dof)) / dof
    design = np.stack([np.ones(intensity.size), intensity], axis=1)
    # start from the median of each equal-count intensity bin (χ²_ν/ν's median divided out)
    bins = np.array_split(np.argsort(intensity, kind="stable"),
                          max(2, min(32, intensity.size // 50)))
    med = np.array([np.median(var[b]) for b in bins]) / (float(chi2.median(dof)) / dof)
    start = np.stack([np.ones(len(bins)), [intensity[b].mean() for b in bins]], axis=1)
    coef, *_ = np.linalg.lstsq(start, med, rcond=None)
    keep = np.zeros(intensity.size, bool)
    for _ in range(20):
        new = var <= limit * np.maximum(design @ coef, 1e-3)
        if new.sum() < 100 or np.array_equal(new, keep):
            break
        keep = new
        coef, *_ = np.linalg.lstsq(design[keep], var[keep], rcond=None)
    return float(coef[0]), float(coef[1])
