"""Depth and reason images for display: turbo colormap, colour bar, legend (PNG bytes)."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from app.core.encoding import png_bytes
from app.core.limits import DEFAULT_DEPTH_RANGE_MM
from app.core.reasons import Reason

U8 = npt.NDArray[np.uint8]

#: RGB colour of each reason code in :func:`reason_png`.
REASON_COLORS: dict[Reason, tuple[int, int, int]] = {
    Reason.OK: (40, 170, 60),
    Reason.LOW_MODULATION: (70, 70, 70),
    Reason.SATURATED: (255, 255, 255),
    Reason.UNWRAP_INCONSISTENT: (230, 50, 50),
    Reason.OUTSIDE_VOLUME: (60, 100, 235),
    Reason.MODEL_SINGULAR: (240, 200, 0),
    Reason.OUTSIDE_FIELD: (150, 60, 200),
    Reason.UNCERTAIN: (240, 140, 30),
    Reason.MOTION: (0, 230, 255),
}
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _check_range(range_mm: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in range_mm)
    except (TypeError, ValueError):
        raise ValueError(f"range_mm: expected (min, max), got {range_mm!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"range_mm: need finite min < max, got {range_mm!r}")
    return lo, hi


def depth_colormap(depth: npt.ArrayLike,
                   range_mm: tuple[float, float] = DEFAULT_DEPTH_RANGE_MM) -> U8:
    """Turbo-coloured depth.

    Args:
        depth: (H, W) heights, mm; NaN (invalid) is drawn black.
        range_mm: (min, max) heights mapped to the two ends of the colormap; values
            outside are clipped.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth: expected shape (H, W), got {d.shape}")
    lo, hi = _check_range(range_mm)
    finite = np.isfinite(d)
    scaled = np.clip((np.where(finite, d, lo) - lo) * (255.0 / (hi - lo)), 0.0, 255.0)
    bgr = cv2.applyColorMap(np.rint(scaled).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = np.ascontiguousarray(bgr[..., ::-1])
    rgb[~finite] = 0
    return np.asarray(rgb, dtype=np.uint8)


def _nice_step(span: float, max_ticks: int) -> float:
    raw = span / max(max_ticks, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * mag >= raw:
            return m * mag
    return 10.0 * mag


def render_depth_png(depth: npt.ArrayLike, range_mm: tuple[float, float] = DEFAULT_DEPTH_RANGE_MM,
                     *, unit: str = "mm") -> bytes:
    """PNG of :func:`depth_colormap` with a vertical colour bar and tick labels in
    ``unit`` at the right."""
    img = depth_colormap(depth, range_mm)
    lo, hi = _check_range(range_mm)
    h = max(img.shape[0], 120)
    bar_w, label_w, pad = 18, 78, 10
    canvas = np.full((h, img.shape[1] + pad + bar_w + label_w, 3), 255, np.uint8)
    canvas[: img.shape[0], : img.shape[1]] = img
    top, bottom = 10, h - 10
    levels = np.linspace(255.0, 0.0, bottom - top).astype(np.uint8)[:, None]
    bar = cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)[:, :, ::-1]
    x0 = img.shape[1] + pad
    canvas[top:bottom, x0 : x0 + bar_w] = bar
    step = _nice_step(hi - lo, max(2, (bottom - top) // 40))
    tick = math.ceil(lo / step) * step
    while tick <= hi + 1e-9 * (hi - lo):
        y = int(round(bottom - 1 - (tick - lo) / (hi - lo) * (bottom - top - 1)))
        cv2.line(canvas, (x0 + bar_w, y), (x0 + bar_w + 4, y), (0, 0, 0), 1)
        label = f"{tick:g} {unit}"
        cv2.putText(canvas, label, (x0 + bar_w + 7, y + 4), _FONT, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
        tick += step
    return png_bytes(canvas, rgb=True)


def reason_png(reason: npt.ArrayLike) -> bytes:
    """PNG of a reason-code map (one colour per :class:`Reason`) with a legend below."""
    r = np.asarray(reason)
    if r.ndim != 2 or not np.issubdtype(r.dtype, np.integer):
        raise ValueError(f"reason: expected an (H, W) integer array, got {r.dtype} {r.shape}")
    # drawn in OpenCV's B, G, R order and written without PNG row filters: a batch writes
    # one per set, and flat colours compress as well unfiltered
    lut = np.zeros((256, 3), np.uint8)
    lut[:] = (255, 0, 255)  # unknown codes stand out
    for code, color in REASON_COLORS.items():
        lut[int(code)] = color[::-1]
    codes = np.clip(r, 0, 255).astype(np.uint8, copy=False)
    row_h = 18
    width = max(r.shape[1], 230)
    canvas = np.full((r.shape[0] + 6 + row_h * len(REASON_COLORS), width, 3), 255, np.uint8)
    np.take(lut, codes, axis=0, out=canvas[: r.shape[0], : r.shape[1]])
    if r.dtype == np.uint8:
        counts = np.bincount(codes.ravel(), minlength=256)
    else:  # codes outside 0..255 were clipped for the colours, not for the counts
        counts = np.zeros(256, np.int64)
        for code in REASON_COLORS:
            counts[int(code)] = np.count_nonzero(r == code)
    total = max(r.size, 1)
    for i, (code, color) in enumerate(REASON_COLORS.items()):
        y = r.shape[0] + 6 + i * row_h
        bgr = color[::-1]
        cv2.rectangle(canvas, (4, y + 3), (16, y + 14), bgr, -1)
        cv2.rectangle(canvas, (4, y + 3), (16, y + 14), (0, 0, 0), 1)
        frac = 100.0 * float(counts[int(code)]) / total
        cv2.putText(canvas, f"{int(code)} {code.name.lower()} {frac:.1f}%", (22, y + 13), _FONT,
                    0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return png_bytes(canvas, filter_none=True)
