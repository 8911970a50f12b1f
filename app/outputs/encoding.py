"""Result images and files as bytes (NPY, 16-bit PNG in µm, colormap PNG/JPEG, PLY).

Encodings are cached on the :class:`LiveResult`, so any number of clients share one.
"""

from __future__ import annotations

import json
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from app.core.encoding import npy_bytes as npy_bytes  # re-exported for the result routes
from app.core.encoding import png_bytes
from app.core.errors import InvalidRequest
from app.core.limits import DEFAULT_DEPTH_RANGE_MM

DEFAULT_RANGE_MM = DEFAULT_DEPTH_RANGE_MM  # the outputs' name for it

def reason_colors() -> dict[int, tuple[str, tuple[int, int, int]]]:
    """reason code → (name, RGB), every :class:`~app.core.reasons.Reason` (MOTION included)."""
    from app.recon.colormap import REASON_COLORS

    out = {int(code): (code.name.lower(), tuple(int(c) for c in rgb))
           for code, rgb in REASON_COLORS.items()}
    return out  # type: ignore[return-value]


def reason_legend() -> dict[str, Any]:
    return {str(code): {"name": name, "rgb": list(rgb)}
            for code, (name, rgb) in reason_colors().items()}


def depth_png_um(depth_mm: npt.NDArray[np.float32]) -> bytes:
    """16-bit PNG of depth in micrometres, 0 = invalid.

    Valid heights are clipped to 1–65535 µm (0.001–65.535 mm): heights at or below the
    reference plane show as 1 µm, so a valid pixel is never confused with an invalid one.
    """
    d = np.asarray(depth_mm, np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth_mm: expected (H, W), got shape {d.shape}")
    finite = np.isfinite(d)
    um = np.zeros(d.shape, np.uint16)
    um[finite] = np.clip(np.rint(d[finite] * 1000.0), 1, 65535).astype(np.uint16)
    return png_bytes(um)


def check_range_mm(min_mm: float | None, max_mm: float | None) -> tuple[float, float]:
    """The colormap range from optional bounds (user input); ``InvalidRequest`` if not min < max."""
    lo = DEFAULT_RANGE_MM[0] if min_mm is None else float(min_mm)
    hi = DEFAULT_RANGE_MM[1] if max_mm is None else float(max_mm)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise InvalidRequest(f"min_mm/max_mm: need finite min < max, got {lo}, {hi}")
    return lo, hi


def depth_color_png(depth_mm: npt.NDArray[np.float32], range_mm: tuple[float, float]) -> bytes:
    """Turbo colormap with colour bar (the engine's renderer), PNG."""
    from app.recon.colormap import render_depth_png

    return bytes(render_depth_png(depth_mm, range_mm=range_mm))


def depth_color_jpeg(
    depth_mm: npt.NDArray[np.float32], range_mm: tuple[float, float], *, max_width: int = 960,
    quality: int = 80
) -> bytes:
    """Turbo colormap of the depth, down-scaled to ``max_width`` pixels, JPEG (no colour bar:
    the page draws its own). Scaled before colouring, nearest-neighbour, so invalid stays black."""
    from app.recon.colormap import depth_colormap

    d: npt.NDArray[Any] = np.asarray(depth_mm, np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth_mm: expected (H, W), got shape {d.shape}")
    if d.shape[1] > max_width:
        size = (max_width, max(1, round(d.shape[0] * max_width / d.shape[1])))
        d = cv2.resize(d, size, interpolation=cv2.INTER_NEAREST)
    bgr = np.ascontiguousarray(depth_colormap(d, range_mm)[..., ::-1])
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise OSError("JPEG encoding failed")
    return buf.tobytes()


def texture_u8(texture: npt.NDArray[np.float32], full_scale: float) -> npt.NDArray[np.uint8]:
    """Texture A + B scaled by the sensor's full scale to uint8 (fixed scale: no flicker)."""
    t: npt.NDArray[np.float32] = (np.nan_to_num(np.asarray(texture, np.float32), nan=0.0)
                                  * (255.0 / float(full_scale)))
    return np.clip(t, 0, 255).astype(np.uint8)


def texture_png(texture: npt.NDArray[np.float32], full_scale: float) -> bytes:
    return png_bytes(texture_u8(texture, full_scale))


def reason_png(reason: npt.NDArray[np.uint8]) -> bytes:
    """Reason codes as colours (see :func:`reason_legend`; unknown codes magenta), PNG."""
    lut = np.zeros((256, 3), np.uint8)
    lut[:] = (255, 0, 255)
    for code, (_, rgb) in reason_colors().items():
        lut[code] = rgb[::-1]  # OpenCV writes BGR
    return png_bytes(lut[np.asarray(reason, np.uint8)])


def ply_bytes(points: npt.NDArray[np.float32], valid: npt.NDArray[np.bool_], intensity: Any,
              sigma: npt.NDArray[np.float32] | None = None,
              sigma_noise: npt.NDArray[np.float32] | None = None,
              sigma_model: npt.NDArray[np.float32] | None = None) -> bytes:
    from app.capture.ply import ply_bytes as encode

    return bytes(encode(points, valid, intensity, sigma, sigma_noise=sigma_noise,
                        sigma_model=sigma_model))


def legend_header() -> str:
    return json.dumps({k: v["name"] for k, v in reason_legend().items()})
