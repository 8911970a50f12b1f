"""The camera's temporal noise from one fringe set: the residual of the N-step fit.

With N > 3 phase steps the sinusoid ``A + B cos(φ + δ_n)`` leaves N − 3 degrees of freedom
per frequency and pixel; their residual sum of squares estimates σ_I² there. Regressing
it on the pixel's mean intensity over the whole image gives the shot + read model
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

from app.core.schedule import PatternSchedule
from app.recon.phase import check_stack
from app.recon.sensor import NoiseSource, SensorNoise

MAX_PIXELS = 200_000  # a regular subsample is plenty for two parameters


def estimate_sensor_noise(frames: Any, schedule: PatternSchedule, *, max_code: int | None = None) -> SensorNoise:
    """Shot + read noise of the camera from the N-step fit residual of one fringe set.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = ``schedule.n_frames``.
        schedule: the pattern schedule; needs ``steps`` N > 3.
        max_code: sensor maximum code (pixels reaching it are left out); None → dtype max.

    Returns:
        :class:`~app.recon.reconstructor.SensorNoise` fitted to the residual variance
        against mean intensity (gain and read noise clipped at 0).

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
    basis = np.stack([np.ones(n)] + [f(h * delta) for h in range(1, harmonics + 1) for f in (np.cos, np.sin)], 1)
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
        raise ValueError("frames: fewer than 100 unsaturated, non-black pixels to estimate the noise from")
    design = np.stack([np.ones(int(usable.sum())), intensity[usable]], axis=1)
    (read_var, gain), *_ = np.linalg.lstsq(design, var[usable], rcond=None)
    return SensorNoise(gain_dn_per_e=max(float(gain), 0.0), read_noise_dn=math.sqrt(max(float(read_var), 0.0)))




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
