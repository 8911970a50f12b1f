"""Point-cloud arrays for the 3-D view: decimation, colours, previews, first viewpoint.

Pure numpy/OpenCV (no viser), so these are testable and reusable on their own. Colours
come from the same TURBO colormap and range as the REST colormap and the dashboard.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from app.outputs.change import delta_colormap
from app.outputs.encoding import DEFAULT_RANGE_MM
from app.outputs.encoding import texture_u8 as _texture_u8
from app.recon.colormap import depth_colormap
from app.service.reconstruction import LiveResult

COLOR_MODES = ("height", "texture", "sigma", "change")
CHANGE_RANGE_MM = 1.0  # the change colours span ±1 mm (blue sink, white none, red rise)
SIGMA_RANGE_MM = (0.0, 0.1)  # colour range of the 1-σ depth noise
PANEL_WIDTH_PX = 360  # GUI images are downscaled to this width: they are previews


def decimation_step(height: int, width: int, max_points: int) -> int:
    """Smallest grid stride ``s`` with ``ceil(H/s)·ceil(W/s) <= max_points``."""
    if max_points < 1:
        raise ValueError(f"max_points: must be >= 1, got {max_points}")
    step = max(1, math.isqrt(max(0, height * width - 1) // max_points))
    while math.ceil(height / step) * math.ceil(width / step) > max_points:
        step += 1
    return step


def cloud_arrays(
    result: LiveResult,
    max_points: int,
    color_mode: str = "height",
    range_mm: tuple[float, float] = DEFAULT_RANGE_MM,
    change_mm: npt.NDArray[np.float32] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8], int]:
    """Decimated valid points of a result and their colours.

    Parameters
    ----------
    result
        Has ``points`` (H, W, 3) float mm, ``valid`` (H, W) bool, ``depth`` (H, W) float mm,
        ``texture`` (H, W) float and ``full_scale`` (the sensor's, for the texture), like
        :class:`app.service.reconstruction.LiveResult`.
    max_points : int
        Upper bound on the returned count (a regular grid stride, so the cloud keeps
        the image's sampling pattern).
    color_mode : {"height", "texture", "sigma", "change"}
        ``sigma``: the 1-σ depth noise (``result.sigma``, mm) over 0–0.1 mm.
    range_mm : (float, float)
        Height colour range.
    change_mm : (H, W) float32 or None
        ``change``: Δ against the change reference, mm (NaN, or None: drawn black), on the
        diverging scale of :mod:`app.outputs.change` over ±1 mm.

    Returns
    -------
    points : (N, 3) float32 mm, N <= max_points
    colors : (N, 3) uint8 RGB
    step : int, the grid stride used
    """
    if color_mode not in COLOR_MODES:
        raise ValueError(f"color_mode: must be one of {COLOR_MODES}, got {color_mode!r}")
    points = np.asarray(result.points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"result.points: expected (H, W, 3), got {points.shape}")
    h, w = points.shape[:2]
    step = decimation_step(h, w, max_points)
    sub = points[::step, ::step]
    keep = np.asarray(result.valid)[::step, ::step] & np.isfinite(sub).all(axis=2)
    xyz = np.ascontiguousarray(sub[keep], dtype=np.float32)
    if color_mode == "height":
        colors = depth_colormap(np.asarray(result.depth)[::step, ::step], range_mm)[keep]
    elif color_mode == "sigma":
        sigma = getattr(result, "sigma", None)
        sig = np.full((h, w), np.nan, np.float32) if sigma is None else np.asarray(sigma)
        colors = depth_colormap(sig[::step, ::step], SIGMA_RANGE_MM)[keep]
    elif color_mode == "change":
        delta = (np.full((h, w), np.nan, np.float32)
                 if change_mm is None or change_mm.shape != (h, w) else change_mm)
        colors = delta_colormap(delta[::step, ::step], CHANGE_RANGE_MM)[keep]
    else:
        gray = texture_u8(result)[::step, ::step][keep]
        colors = np.repeat(gray[:, None], 3, axis=1)
    return xyz, np.ascontiguousarray(colors), step


def texture_u8(result: LiveResult) -> npt.NDArray[np.uint8]:
    """The result's texture as uint8, scaled as the REST texture PNG is."""
    return _texture_u8(np.asarray(result.texture), float(result.full_scale))


def preview(rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    h, w = rgb.shape[:2]
    if w <= PANEL_WIDTH_PX:
        return rgb
    size = (PANEL_WIDTH_PX, max(1, round(h * PANEL_WIDTH_PX / w)))
    return np.asarray(cv2.resize(rgb, size, interpolation=cv2.INTER_AREA))


def point_size_mm(xyz: npt.NDArray[np.float32], step: int, points: npt.NDArray[Any]) -> float:
    """About the spacing of neighbouring decimated points, so the surface looks closed."""
    row = points[points.shape[0] // 2]
    gaps = np.linalg.norm(np.diff(row, axis=0), axis=1)
    gaps = gaps[np.isfinite(gaps)]
    if gaps.size == 0 or xyz.size == 0:
        return 0.2
    return float(np.clip(np.median(gaps) * step * 1.2, 0.01, 5.0))


def initial_view(
    xyz: npt.NDArray[np.float32], tilt_deg: float = 25.0
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], float]:
    """A first viewpoint for a cloud seen from the camera origin.

    The camera centre rotated by ``tilt_deg`` about the cloud's median, upward (−y),
    looking at the median; the vertical field of view frames the central 96 % of the
    points with a margin.

    Returns
    -------
    position, look_at : (3,) float64 mm
    fov_rad : float
    """
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise ValueError(f"xyz: expected (N, 3) with N > 0, got {xyz.shape}")
    centre = np.median(xyz, axis=0).astype(np.float64)
    back = -centre  # from the look-at point to the scope's camera centre
    t = np.deg2rad(tilt_deg)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(t), np.sin(t)], [0.0, -np.sin(t), np.cos(t)]])
    position = centre + rot_x @ back
    distance = float(np.linalg.norm(back)) or 1.0
    lo, hi = np.percentile(xyz, [2.0, 98.0], axis=0)
    half_extent = 0.5 * float(max(hi[0] - lo[0], hi[1] - lo[1]))
    fov_rad = float(np.clip(2.4 * np.arctan2(half_extent, distance), np.deg2rad(20),
                            np.deg2rad(90)))
    return position, centre, fov_rad
