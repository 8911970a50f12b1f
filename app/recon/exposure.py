"""Auto-exposure: the longest exposure whose sets keep saturation under a limit.

Modulation grows with exposure until pixels clip, so the best exposure is the longest
one below the saturation limit. Saturation is monotonic in exposure, so a bisection over
a ladder of exposures finds it with a handful of real grabbed sets.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.core.limits import EXPOSURE_RANGE_MS
from app.core.reasons import Reason
from app.core.schedule import PatternSchedule
from app.recon.phase import wrapped_phase

#: candidate exposures, ms (roughly geometric: each step ≈ 1.25–1.5×), spanning EXPOSURE_RANGE_MS
LADDER_MS = (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.5, 8.0, 10.0, 12.5, 15.0, 20.0, 25.0, 30.0, 40.0,
             50.0, 65.0, 80.0, 100.0)
#: Default allowed fraction of saturated pixels (0.5 %).
DEFAULT_SATURATION_LIMIT = 0.005


@dataclass(frozen=True)
class ExposureTrial:
    exposure_ms: float
    saturated_fraction: float
    modulation: float


@dataclass
class AutoExposureResult:
    exposure_ms: float
    saturated_fraction: float
    modulation: float
    saturation_limit: float
    trials: list[ExposureTrial] = field(default_factory=list)
    warning: str | None = None


def set_statistics(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16], schedule: PatternSchedule,
    full_scale: int
) -> tuple[float, float]:
    """(saturated fraction, median modulation) of one fringe set.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order.
        schedule: its pattern schedule.
        full_scale: the sensor's saturation code (255, 4095, …).

    Returns:
        Fraction of pixels at ``full_scale`` in any frame, and the median modulation B of
        the finest frequency over the pixels with any signal, in sensor codes.
    """
    if frames.ndim != 3 or frames.shape[0] != schedule.n_frames:
        raise ValueError(f"frames: expected ({schedule.n_frames}, H, W), got {frames.shape}")
    saturated = float((frames.max(axis=0) >= full_scale).mean())
    n = schedule.steps
    finest = frames[-n:]
    wp = wrapped_phase(finest, n, max_code=int(full_scale))
    b = wp.modulation[0]
    lit = wp.background > 0.02 * full_scale
    modulation = float(np.median(b[lit])) if lit.any() else 0.0
    return saturated, modulation


def choose_exposure(
    measure: Callable[[float], tuple[float, float]],
    *,
    saturation_limit: float = DEFAULT_SATURATION_LIMIT,
    min_exposure_ms: float = EXPOSURE_RANGE_MS[0],
    max_exposure_ms: float = EXPOSURE_RANGE_MS[1],
    ladder_ms: tuple[float, ...] = LADDER_MS,
) -> AutoExposureResult:
    """Bisect ``ladder_ms`` for the longest exposure with saturation ≤ ``saturation_limit``.

    Args:
        measure: exposure_ms → (saturated fraction, modulation) from a real grabbed set.
        saturation_limit: allowed fraction of saturated pixels (0.005 = 0.5 %).
        min_exposure_ms, max_exposure_ms: bounds of the search, ms.

    Returns:
        The chosen exposure and every trial. Among the trials under the limit the one with
        the highest modulation wins (ties → the longer exposure).
    """
    if not (0.0 <= saturation_limit < 1.0):
        raise ValueError(f"saturation_limit: must be within [0, 1), got {saturation_limit}")
    if not (math.isfinite(min_exposure_ms) and math.isfinite(max_exposure_ms)
            and 0 < min_exposure_ms <= max_exposure_ms):
        raise ValueError("max_exposure_ms: need 0 < min <= max, got "
                         f"{min_exposure_ms}, {max_exposure_ms}")
    ladder = [e for e in ladder_ms if min_exposure_ms <= e <= max_exposure_ms]
    if not ladder or ladder[-1] != max_exposure_ms:
        ladder.append(max_exposure_ms)
    if ladder[0] != min_exposure_ms:
        ladder.insert(0, min_exposure_ms)
    trials: dict[float, ExposureTrial] = {}

    def trial(e: float) -> ExposureTrial:
        if e not in trials:
            sat, mod = measure(e)
            trials[e] = ExposureTrial(e, sat, mod)
        return trials[e]

    # Invariant: ladder[lo] is under the limit (or is the shortest), ladder[hi] is over it.
    lo, hi = 0, len(ladder) - 1
    if trial(ladder[hi]).saturated_fraction <= saturation_limit:
        lo = hi
    else:
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if trial(ladder[mid]).saturated_fraction <= saturation_limit:
                lo = mid
            else:
                hi = mid
    first = trial(ladder[lo])
    ok = [t for t in trials.values() if t.saturated_fraction <= saturation_limit]
    warning = None
    if ok:
        best = max(ok, key=lambda t: (t.modulation, t.exposure_ms))
    else:
        best = first
        warning = f"saturation above {saturation_limit:.2%} even at {first.exposure_ms} ms"
    return AutoExposureResult(
        exposure_ms=best.exposure_ms, saturated_fraction=best.saturated_fraction,
        modulation=best.modulation, saturation_limit=saturation_limit,
        trials=sorted(trials.values(), key=lambda t: t.exposure_ms), warning=warning,
    )


def bracket_exposures(base_ms: float, *, stops: float = 2.0,
                      max_exposure_ms: float = EXPOSURE_RANGE_MS[1]) -> tuple[float, ...]:
    """Exposures of a two-set bracket: ``base_ms`` (the auto-exposure's choice, which keeps the
    bright parts unsaturated) and ``stops`` stops more (×2^stops, capped at ``max_exposure_ms``)
    for the dim parts (:mod:`app.recon.fusion`). A base already at the cap gives one exposure.

    Args:
        base_ms: the base exposure, ms, within (0, max_exposure_ms].
        stops: how much longer the second exposure is, in stops (factors of 2), > 0.
        max_exposure_ms: the camera's longest exposure, ms.

    Returns:
        (base_ms,) or (base_ms, longer_ms).
    """
    if not (math.isfinite(max_exposure_ms) and max_exposure_ms > 0):
        raise ValueError(f"max_exposure_ms: must be finite and > 0, got {max_exposure_ms}")
    if not (math.isfinite(base_ms) and 0 < base_ms <= max_exposure_ms):
        raise ValueError(f"base_ms: must be within (0, {max_exposure_ms:g}] ms, got {base_ms}")
    if not (math.isfinite(stops) and stops > 0):
        raise ValueError(f"stops: must be finite and > 0, got {stops}")
    longer = min(base_ms * 2.0**stops, max_exposure_ms)
    return (float(base_ms),) if longer <= base_ms else (float(base_ms), float(longer))



#: an ROI is "mostly dark" when more than this share of it is invalid for low signal
LOW_SIGNAL_SHARE = 0.5


@dataclass(frozen=True)
class LowSignal:
    """Most of an ROI is invalid for low signal, and the exposure the auto-exposure would pick.

    ``share``: fraction of the ROI's pixels LOW_MODULATION or UNCERTAIN; ``exposure_ms`` the
    set's exposure; ``suggested_exposure_ms`` the search's choice predicted from the set.
    """

    share: float
    exposure_ms: float
    suggested_exposure_ms: float

    def message(self) -> str:
        return (f"{100 * self.share:.0f}% of the ROI is invalid for low signal at "
                f"{self.exposure_ms:g} ms: the auto-exposure would choose "
                f"{self.suggested_exposure_ms:g} ms")


def predicted_exposure_ms(peak_dn: npt.NDArray[np.float32], modulation_dn: npt.NDArray[np.float32],
                          exposure_ms: float, full_scale: float, *,
                          saturation_limit: float = DEFAULT_SATURATION_LIMIT) -> float:
    """The exposure :func:`choose_exposure` would pick, predicted from one set's levels.

    Each trial scales the set's per-pixel peak A + B and modulation B (DN) linearly with
    exposure instead of grabbing a set (pixels clipped in the set stay clipped).

    Args:
        peak_dn: (H, W) A + B of the set, DN (NaN ignored).
        modulation_dn: (H, W) finest modulation B, DN (NaN ignored).
        exposure_ms: the set's exposure, ms, > 0.
        full_scale: the sensor's saturation code.
        saturation_limit: as in :func:`choose_exposure`.

    Returns:
        The chosen exposure, ms.
    """
    if not (math.isfinite(exposure_ms) and exposure_ms > 0):
        raise ValueError(f"exposure_ms: must be finite and > 0, got {exposure_ms}")
    if not (math.isfinite(full_scale) and full_scale > 0):
        raise ValueError(f"full_scale: must be finite and > 0, got {full_scale}")
    peak = np.nan_to_num(np.asarray(peak_dn, np.float64)[::2, ::2], nan=0.0)
    mod = np.nan_to_num(np.asarray(modulation_dn, np.float64)[::2, ::2], nan=0.0)
    lit = peak > 0.02 * full_scale
    clipped = peak >= full_scale

    def measure(e: float) -> tuple[float, float]:
        k = e / exposure_ms
        sat = float(((peak * k >= full_scale) | clipped).mean())
        return sat, float(np.median(mod[lit]) * k) if lit.any() else 0.0

    return choose_exposure(measure, saturation_limit=saturation_limit).exposure_ms


def low_signal(reason: npt.NDArray[np.uint8], area: npt.NDArray[np.bool_],
               peak_dn: npt.NDArray[np.float32], modulation_dn: npt.NDArray[np.float32],
               exposure_ms: float, full_scale: float) -> LowSignal | None:
    """:class:`LowSignal` when most of ``area`` is LOW_MODULATION or UNCERTAIN, else None.

    Args:
        reason: (H, W) reason codes of the result; ``area`` (H, W) bool the ROI.
        peak_dn, modulation_dn, exposure_ms, full_scale: as in :func:`predicted_exposure_ms`.
    """
    if reason.shape != area.shape:
        raise ValueError(f"area: shape {area.shape} differs from reason {reason.shape}")
    n = int(area.sum())
    if n == 0:
        return None
    dark = np.isin(reason[area], (int(Reason.LOW_MODULATION), int(Reason.UNCERTAIN)))
    share = float(dark.mean())
    if share <= LOW_SIGNAL_SHARE:
        return None
    return LowSignal(share, float(exposure_ms),
                     predicted_exposure_ms(peak_dn, modulation_dn, exposure_ms, full_scale))
