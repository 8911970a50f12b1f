"""Turbo depth images, colour bar and reason legend."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.recon import depth_colormap, reason_png, render_depth_png
from app.recon.colormap import REASON_COLORS


def _turbo(level: int) -> np.ndarray:
    return cv2.applyColorMap(np.array([[level]], np.uint8), cv2.COLORMAP_TURBO)[0, 0, ::-1]


def test_depth_colormap_ends_clip_and_nan():
    d = np.array([[0.0, 35.0, -5.0, 50.0, np.nan, 17.5]], np.float32)
    rgb = depth_colormap(d)
    assert rgb.shape == (1, 6, 3) and rgb.dtype == np.uint8
    assert (rgb[0, 0] == _turbo(0)).all() and (rgb[0, 1] == _turbo(255)).all()
    assert (rgb[0, 2] == _turbo(0)).all() and (rgb[0, 3] == _turbo(255)).all()
    assert (rgb[0, 4] == 0).all()
    assert (rgb[0, 5] == _turbo(128)).all()
    assert (depth_colormap(np.array([[10.0]]), (10.0, 20.0))[0, 0] == _turbo(0)).all()


def test_depth_png_has_colour_bar():
    d = np.linspace(0, 35, 200 * 150, dtype=np.float32).reshape(150, 200)
    img = cv2.imdecode(np.frombuffer(render_depth_png(d), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[0] == 150 and img.shape[1] > 200 + 40
    bar = img[:, 200 + 10 + 9, ::-1]  # middle of the bar column, RGB
    assert (bar[10] == _turbo(255)).all() and (bar[150 - 11] == _turbo(0)).all()
    labels = img[:, 200 + 10 + 18 + 8 :]
    assert (labels < 100).any()  # dark tick text drawn


def test_reason_png_legend():
    r = np.zeros((30, 40), np.uint8)
    r[:, 20:] = 3
    img = cv2.imdecode(np.frombuffer(reason_png(r), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert img.shape[0] > 30 + 6 * 15 and img.shape[1] >= 230
    assert tuple(img[5, 5]) == REASON_COLORS[0] and tuple(img[5, 25]) == REASON_COLORS[3]


@pytest.mark.parametrize("rng", [(1.0, 1.0), (5.0, 0.0), (0.0, float("nan")), "0,35"])
def test_bad_range(rng):
    with pytest.raises(ValueError, match="^range_mm"):
        depth_colormap(np.zeros((2, 2)), rng)


def test_bad_arrays():
    with pytest.raises(ValueError, match="^depth"):
        depth_colormap(np.zeros(3))
    with pytest.raises(ValueError, match="^reason"):
        reason_png(np.zeros((2, 2), np.float32))
