"""ROI measurements on the latest result (delegating to :mod:`app.analysis`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.errors import InvalidRequest
from app.service.reconstruction import LiveResult


def _f(x: Any) -> float | None:
    """JSON has no NaN: undefined figures are None."""
    return float(x) if x is not None and math.isfinite(float(x)) else None


def low_signal_note(result: LiveResult, roi: tuple[int, int, int, int]) -> dict[str, Any]:
    """When most of ``roi`` is invalid for low signal: that share, and the exposure the
    auto-exposure would choose (predicted from the map's levels); else nothing."""
    from app.analysis import roi_mask
    from app.recon.exposure import low_signal

    dark = low_signal(result.reason, roi_mask(result.reason.shape, roi), result.texture,
                      result.modulation, result.exposure_ms, result.full_scale)
    if dark is None:
        return {}
    return {"low_signal_fraction": dark.share, "suggested_exposure_ms": dark.suggested_exposure_ms,
            "warning": dark.message()}


def plane(result: LiveResult, roi: tuple[int, int, int, int]) -> dict[str, Any]:
    """Plane accuracy/precision/flatness of the points in ``roi`` (paper's DOF-target method)."""
    from app.analysis.plane import plane_accuracy

    try:
        acc = plane_accuracy(result.points, result.valid, roi=roi)
    except ValueError as exc:  # the ROI (the only user input) does not fit the result
        raise InvalidRequest(str(exc)) from None
    return {
        "accuracy_mm": _f(acc.accuracy_mm), "precision_mm": _f(acc.precision_mm),
        "flatness_mm": _f(acc.flatness_mm), "points": int(acc.n_points),
        "extra": {"inlier_fraction": _f(acc.inlier_fraction), "seq": result.seq,
                  "mean_distance_mm": _f(acc.mean_distance_mm), "bins": len(acc.bins),
                  **low_signal_note(result, roi)},
    }


def feature(result: LiveResult, roi: tuple[int, int, int, int], polarity: str = "bright",
            plane_normal: npt.NDArray[np.float64] | None = None) -> dict[str, Any]:
    """Height of a raised feature (e.g. a suture, segmented by intensity)
    over its baseline in ``roi``.

    With the calibration's reference-plane ``plane_normal`` the cross-sections are taken in the
    plane's millimetres, free of the raised crest's parallax (:func:`plane_coordinates`)."""
    from app.analysis.feature import feature_height, plane_coordinates

    try:
        coords = None if plane_normal is None else plane_coordinates(result.points, plane_normal)
        res = feature_height(result.depth, result.texture, result.valid, roi=roi,
                             polarity=None if polarity == "auto" else polarity, coords_mm=coords)
    except ValueError as exc:  # the ROI / polarity (user input) does not fit the result
        raise InvalidRequest(str(exc)) from None
    return {
        "height_mm": _f(res.height_mm), "height_std_mm": _f(res.height_std_mm),
        "count": int(res.count),
        "extra": {"seq": result.seq, "baseline_rms_mm": _f(res.baseline_rms_mm),
                  "height_se_mm": _f(res.height_se_mm), "polarity": res.polarity,
                  "feature_pixels": int(res.mask.sum()), **low_signal_note(result, roi)},
    }
