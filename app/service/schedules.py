"""The schedule table of ``GET /api/schedules``: each registered schedule's predicted
figures at the rig's noise.

The rig's noise comes from the instrument itself: the camera's σ_I model (fitted to the
N-step residual of the newest whole raw set when N > 3, else the generic sensor model the
live engine uses), the modulation B and background A of the newest depth map's valid
pixels, and the calibration's slope |∂z/∂φ| at those pixels, recovered from the map's
own σ (``σ = |∂z/∂φ|·σ_φ`` with the live engine's σ_φ). With no depth map yet the
order-error rate is given for a nominal pixel (A = 0.4, B = 0.3 of full scale) and the
depth σ is unknown (``None``).
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.analysis.schedules import predict_schedule, wrapped_phase_sigma_rad
from app.core.calibration import Calibration
from app.core.schedule import SCHEDULES, PatternSchedule, calibration_mismatch
from app.recon.noise import estimate_sensor_noise
from app.recon.reconstructor import SensorNoise

log = logging.getLogger("fringescope.service.schedules")

MAX_PIXELS = 50_000  # a regular subsample of the valid pixels is plenty for medians and means


def calibration_for_schedule(cal: Calibration, schedule: PatternSchedule) -> Calibration:
    """``cal`` re-stated for ``schedule`` (same depth model, other pattern): the carry-over rule.

    Raises:
        ValueError: the calibration does not apply
        (:func:`~app.core.schedule.calibration_mismatch`).
    """
    reason = calibration_mismatch(cal.pattern, schedule)
    if reason is not None:
        raise ValueError(f"calibration: {reason}")
    if cal.pattern == schedule:
        return cal
    out = copy.copy(cal)
    out.pattern = schedule
    return out


@dataclass(frozen=True)
class RigPixels:
    """What the predictions need of the rig, per sampled pixel (all (P,) float64)."""

    sigma_i: npt.NDArray[np.float64]  # intensity noise per frame, codes
    modulation: npt.NDArray[np.float64]  # B, codes
    slope_mm_per_rad: npt.NDArray[np.float64] | None  # |∂z/∂φ| of the finest phase; None: unknown
    source: str  # "live" | "nominal"


def rig_pixels(result: Any, schedule: PatternSchedule, full_scale: float,
               noise: SensorNoise | None = None) -> RigPixels:
    """The rig's per-pixel noise, contrast and slope from the newest depth map (or a nominal pixel).

    Args:
        result: the newest :class:`~app.service.reconstruction.LiveResult` (or None).
        schedule: the schedule it was taken with (its N gives the engine's σ_φ).
        full_scale: the sensor's maximum code.
        noise: the camera's noise model; None: :meth:`SensorNoise.typical` (the live engine's).
    """
    engine_noise = SensorNoise.typical(round(full_scale))
    model = noise or engine_noise
    if result is None or result.sigma is None:
        a, b = 0.4 * full_scale, 0.3 * full_scale
        return RigPixels(np.sqrt(model.variance_dn2(np.array([a]))), np.array([b]), None, "nominal")
    keep = result.valid & np.isfinite(result.sigma) & (result.modulation > 0)
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return rig_pixels(None, schedule, full_scale, noise)
    idx = idx[:: max(1, idx.size // MAX_PIXELS)]
    b = result.modulation.ravel()[idx].astype(np.float64)
    a = result.texture.ravel()[idx].astype(np.float64) - b
    engine_sig_phi = wrapped_phase_sigma_rad(np.sqrt(engine_noise.variance_dn2(a)), b,
                                             schedule.steps)
    slope = result.sigma.ravel()[idx].astype(np.float64) / engine_sig_phi
    return RigPixels(np.sqrt(model.variance_dn2(a)), b, slope, "live")


def sensor_noise_of(frames: Any, schedule: PatternSchedule, max_code: int) -> SensorNoise | None:
    """The camera's noise fitted to one whole raw set (None when N = 3 or the
    set does not allow it)."""
    if schedule.steps <= 3:
        return None
    try:
        return estimate_sensor_noise(frames, schedule, max_code=max_code)
    except ValueError as exc:
        log.debug("noise estimate: %s", exc)
        return None


def schedule_table(pixels: RigPixels, active: PatternSchedule,
                   calibration: Calibration | None) -> list[dict[str, Any]]:
    """One row per registered schedule for ``GET /api/schedules``."""
    rows = []
    for name, s in SCHEDULES.items():
        slope = pixels.slope_mm_per_rad if pixels.slope_mm_per_rad is not None else 1.0
        pred = predict_schedule(s, pixels.sigma_i, pixels.modulation, slope)
        mismatch = None if calibration is None else calibration_mismatch(calibration.pattern, s)
        rows.append({
            "name": name,
            "frequencies": list(s.frequencies),
            "steps": s.steps,
            "unwrap": s.unwrap,
            "frames_per_depth": s.n_frames,
            "predicted_sigma_mm": (None if pixels.slope_mm_per_rad is None
                                   else round(pred.sigma_mm, 6)),
            "predicted_sigma_phi_rad": round(pred.sigma_phi_rad, 6),
            "predicted_order_error_rate": float(f"{pred.order_error_rate:.3g}"),
            "prediction_source": pixels.source,
            "calibration_applies": None if calibration is None else mismatch is None,
            "calibration_note": mismatch,
            "active": s == active,
        })
    return rows
