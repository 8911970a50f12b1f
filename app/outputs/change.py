"""Images of a change map: a diverging blue–white–red colormap in mm, the changed contour."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from app.core.encoding import png_bytes

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]

#: default half-range of the change colormap: ±1 mm
DEFAULT_CHANGE_RANGE_MM = 1.0
#: colour of the changed region's contour (RGB)
CONTOUR_RGB = (20, 20, 20)
_FONT = cv2.FONT_HERSHEY_SIMPLEX
# anchors of the diverging map at -1, 0, +1: sink blue, no change white, rise red
_ANCHORS = np.array([[33, 102, 172], [247, 247, 247], [178, 24, 43]], np.float32)


def check_change_range(range_mm: float) -> float:
    """The half-range R (mm) of the colormap: finite and > 0, else ValueError naming it."""
    if not (isinstance(range_mm, (int, float)) and math.isfinite(range_mm) and range_mm > 0):
        raise ValueError(f"range_mm: must be a finite number > 0, got {range_mm!r}")
    return float(range_mm)


def _lut() -> U8:
    # 255 entries: entry 127 is exactly 0 (white)
    x = np.linspace(-1.0, 1.0, 255, dtype=np.float32)[:, None]
    lo = _ANCHORS[0] + (x + 1.0) * (_ANCHORS[1] - _ANCHORS[0])
    hi = _ANCHORS[1] + x * (_ANCHORS[2] - _ANCHORS[1])
    out: U8 = np.rint(np.where(x < 0, lo, hi)).astype(np.uint8)
    return out


_LUT = _lut()


def delta_colormap(delta_mm: F32, range_mm: float = DEFAULT_CHANGE_RANGE_MM,
                   changed: npt.NDArray[np.bool_] | None = None) -> U8:
    """(H, W, 3) uint8 RGB of Δ: −R blue, 0 white, +R red (clipped beyond), NaN black; with
    ``changed`` the outline of the changed region drawn over it."""
    d = np.asarray(delta_mm, np.float32)
    if d.ndim != 2:
        raise ValueError(f"delta_mm: expected (H, W), got {d.shape}")
    r = check_change_range(range_mm)
    finite = np.isfinite(d)
    idx = np.rint((np.clip(np.where(finite, d, 0.0) / r, -1.0, 1.0) + 1.0) * 127.0)
    rgb = np.ascontiguousarray(_LUT[idx.astype(np.uint8)])
    rgb[~finite] = 0
    if changed is not None:
        if changed.shape != d.shape:
            raise ValueError(f"changed: shape {changed.shape} differs from {d.shape}")
        contours, _ = cv2.findContours(changed.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(rgb, contours, -1, CONTOUR_RGB, max(1, d.shape[1] // 700))
    return rgb


def delta_png(delta_mm: F32, changed: npt.NDArray[np.bool_] | None = None,
              range_mm: float = DEFAULT_CHANGE_RANGE_MM) -> bytes:
    """PNG of :func:`delta_colormap` with a vertical colour bar labelled in mm at the right."""
    img = delta_colormap(delta_mm, range_mm, changed)
    r = check_change_range(range_mm)
    h = max(img.shape[0], 120)
    bar_w, label_w, pad = 18, 90, 10
    canvas = np.full((h, img.shape[1] + pad + bar_w + label_w, 3), 255, np.uint8)
    canvas[: img.shape[0], : img.shape[1]] = img
    top, bottom = 10, h - 10
    levels = np.rint(np.linspace(254.0, 0.0, bottom - top)).astype(np.uint8)
    x0 = img.shape[1] + pad
    canvas[top:bottom, x0:x0 + bar_w] = _LUT[levels][:, None, :]
    for frac in (1.0, 0.5, 0.0, -0.5, -1.0):
        y = int(round(top + (1.0 - frac) / 2.0 * (bottom - top - 1)))
        cv2.line(canvas, (x0 + bar_w, y), (x0 + bar_w + 4, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"{frac * r:+g} mm", (x0 + bar_w + 7, y + 4), _FONT, 0.38,
                    (0, 0, 0), 1, cv2.LINE_AA)
    return png_bytes(canvas, rgb=True)


def delta_color_png(delta_mm: F32, changed: npt.NDArray[np.bool_] | None = None,
                    range_mm: float = DEFAULT_CHANGE_RANGE_MM) -> bytes:
    """PNG of :func:`delta_colormap` alone (same size as the map), for overlays."""
    return png_bytes(delta_colormap(delta_mm, range_mm, changed), rgb=True)


__all__ = ["DEFAULT_CHANGE_RANGE_MM", "check_change_range", "delta_color_png",
           "delta_colormap", "delta_png"]
