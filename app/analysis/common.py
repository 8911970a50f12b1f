"""Shared input handling for the analysis functions: ROI and validity selection."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def roi_mask(shape: tuple[int, int],
             roi: tuple[int, int, int, int] | None) -> npt.NDArray[np.bool_]:
    """(H, W) bool mask of the pixel box ``roi = (x0, y0, x1, y1)`` (x1, y1
    exclusive); all if None."""
    h, w = shape
    mask = np.zeros((h, w), bool)
    if roi is None:
        mask[:] = True
        return mask
    if len(roi) != 4:
        raise ValueError(f"roi: expected (x0, y0, x1, y1), got {roi!r}")
    x0, y0, x1, y1 = (int(r) for r in roi)
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise ValueError(f"roi: ({x0}, {y0}, {x1}, {y1}) is empty or outside the {w}x{h} image")
    mask[y0:y1, x0:x1] = True
    return mask


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """Parse ``"x0,y0,x1,y1"`` into a tuple of four integers."""
    parts = text.split(",")
    try:
        vals = tuple(int(p) for p in parts)
    except ValueError:
        raise ValueError(f"roi: expected x0,y0,x1,y1 integers, got {text!r}") from None
    if len(vals) != 4:
        raise ValueError(f"roi: expected x0,y0,x1,y1 integers, got {text!r}")
    return vals


def select_points(points: npt.ArrayLike, valid: npt.ArrayLike | None,
                  roi: tuple[int, int, int, int] | None) -> npt.NDArray[np.float64]:
    """Finite (n, 3) float64 points from a (H, W, 3) map or (n, 3) array,
    masked by valid and ROI."""
    pts = np.asarray(points, np.float64)
    if pts.ndim == 3 and pts.shape[2] == 3:
        mask = roi_mask(pts.shape[:2], roi)
    elif pts.ndim == 2 and pts.shape[1] == 3:
        if roi is not None:
            raise ValueError("roi: only applies to (H, W, 3) point maps")
        mask = np.ones(pts.shape[0], bool)
    else:
        raise ValueError(f"points: expected (H, W, 3) or (n, 3), got {pts.shape}")
    if valid is not None:
        v = np.asarray(valid, bool)
        if v.shape != mask.shape:
            raise ValueError(f"valid: shape {v.shape} does not match points {mask.shape}")
        mask &= v
    mask &= np.all(np.isfinite(pts), axis=-1)
    return pts[mask]
