"""Comparison of a reconstruction with ground truth (the simulator's, or a reference scan)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


@dataclass
class DepthErrors:
    """Depth − truth figures, split by the calibrated volume.

    Attributes:
        inside_pixels: pixels whose true height lies in the calibrated range.
        valid_fraction: share of those the reconstruction marked valid.
        mean_error_mm, max_abs_error_mm, rms_error_mm: over valid inside pixels, mm.
        outside_pixels / outside_valid: pixels with true height outside the range, and how
            many of them were still reported valid.
        outside_max_abs_error_mm: worst |error| of those valid outside pixels (NaN if none).
        within_bin_std_mm: pooled standard deviation of the error within bins of true
            height (bin width = range/√N): the random part, comparable with a noise floor.
    """

    inside_pixels: int
    valid_fraction: float
    mean_error_mm: float
    max_abs_error_mm: float
    rms_error_mm: float
    outside_pixels: int
    outside_valid: int
    outside_max_abs_error_mm: float
    within_bin_std_mm: float


def depth_errors(depth: npt.ArrayLike, truth: npt.ArrayLike, height_range_mm: tuple[float, float],
                 *, mask: npt.ArrayLike | None = None) -> DepthErrors:
    """Compare a depth map with the true depth.

    Args:
        depth: (H, W) measured height, mm, NaN invalid.
        truth: (H, W) true height, mm, NaN where there is no object.
        height_range_mm: (min, max) calibrated heights, mm.
        mask: optional (H, W) bool region to evaluate (e.g. one object).
    """
    d = np.asarray(depth, np.float64)
    t = np.asarray(truth, np.float64)
    if d.ndim != 2 or d.shape != t.shape:
        raise ValueError(f"truth: shape {t.shape} must equal depth {d.shape} (2-D)")
    lo, hi = (float(x) for x in height_range_mm)
    region = np.isfinite(t)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != d.shape:
            raise ValueError(f"mask: shape {m.shape} does not match depth {d.shape}")
        region &= m
    inside = region & (t >= lo) & (t <= hi)
    outside = region & ~inside
    valid = np.isfinite(d)
    err = d - t
    e_in = err[inside & valid]
    e_out = err[outside & valid]
    return DepthErrors(
        inside_pixels=int(inside.sum()),
        valid_fraction=float((inside & valid).sum() / max(1, inside.sum())),
        mean_error_mm=float(e_in.mean()) if e_in.size else math.nan,
        max_abs_error_mm=float(np.abs(e_in).max()) if e_in.size else math.nan,
        rms_error_mm=float(np.sqrt(np.mean(e_in**2))) if e_in.size else math.nan,
        outside_pixels=int(outside.sum()),
        outside_valid=int(e_out.size),
        outside_max_abs_error_mm=float(np.abs(e_out).max()) if e_out.size else math.nan,
        within_bin_std_mm=_pooled_std(t[inside & valid], e_in),
    )


def _pooled_std(key: F64, values: F64) -> float:
    n = values.size
    if n < 3:
        return math.nan
    n_bins = max(1, math.ceil(math.sqrt(n)))
    lo, hi = float(key.min()), float(key.max())
    width = (hi - lo) / n_bins if hi > lo else 1.0
    which = np.clip(((key - lo) / width).astype(np.int64), 0, n_bins - 1)
    counts = np.bincount(which, minlength=n_bins).astype(np.float64)
    sums = np.bincount(which, weights=values, minlength=n_bins)
    sq = np.bincount(which, weights=values**2, minlength=n_bins)
    used = counts > 1
    ss = sq[used] - sums[used] ** 2 / counts[used]
    dof = float((counts[used] - 1).sum())
    return float(math.sqrt(max(0.0, ss.sum()) / dof)) if dof > 0 else math.nan


def perpendicular_noise_mm(height_noise_mm: npt.ArrayLike, points: npt.ArrayLike,
                           plane_normal: npt.ArrayLike, reference_normal: npt.ArrayLike) -> F64:
    """Height noise (mm) converted to noise of the distance to a plane of ``plane_normal``.

    A height change dh moves a point along its camera ray by X/(n_ref·X)·dh, so the
    distance to the plane changes by (n·X)/(n_ref·X)·dh.

    Args:
        height_noise_mm: (...) σ of the height, mm.
        points: (..., 3) camera-frame points, mm.
        plane_normal, reference_normal: (3,) unit normals.
    """
    x = np.asarray(points, np.float64)
    n = np.asarray(plane_normal, np.float64)
    nr = np.asarray(reference_normal, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(np.asarray(height_noise_mm, np.float64) * (x @ n) / (x @ nr))
