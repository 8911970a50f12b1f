"""The change map's images and the 3-D view's change colours."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.outputs.change import delta_color_png, delta_colormap, delta_png
from app.outputs.cloud import cloud_arrays
from tests.helpers.outputs import surface_result


def test_the_diverging_map_is_blue_white_red_and_black_where_not_compared():
    d = np.array([[-2.0, -1.0, 0.0, 1.0, 2.0, np.nan]], np.float32)
    rgb = delta_colormap(d, 1.0)
    assert tuple(rgb[0, 0]) == tuple(rgb[0, 1]) == (33, 102, 172)  # clipped at -R
    assert tuple(rgb[0, 2]) == (247, 247, 247)
    assert tuple(rgb[0, 3]) == tuple(rgb[0, 4]) == (178, 24, 43)
    assert tuple(rgb[0, 5]) == (0, 0, 0)
    with pytest.raises(ValueError, match="range_mm"):
        delta_colormap(d, 0.0)


def test_the_changed_region_is_outlined_and_the_png_has_a_bar():
    d = np.zeros((60, 80), np.float32)
    changed = np.zeros(d.shape, bool)
    changed[20:40, 30:50] = True
    d[changed] = 0.5
    rgb = delta_colormap(d, 1.0, changed)
    assert tuple(rgb[20, 35]) == (20, 20, 20)  # the contour on the region's edge
    assert rgb[30, 40, 0] > rgb[30, 40, 2]  # a rise inside: red side
    png = cv2.imdecode(np.frombuffer(delta_png(d, changed, 1.0), np.uint8), cv2.IMREAD_COLOR)
    assert png.shape[0] >= 120 and png.shape[1] > 80 + 100
    overlay = cv2.imdecode(np.frombuffer(delta_color_png(d, changed), np.uint8), cv2.IMREAD_COLOR)
    assert overlay.shape[:2] == d.shape


def test_the_cloud_colours_by_change():
    res = surface_result()
    change = np.zeros(res.depth.shape, np.float32)
    change[:, :80] = -1.0  # the left half sank 1 mm
    change[:, 80:] = 1.0
    xyz, rgb, step = cloud_arrays(res, 100_000, "change", change_mm=change)
    left = xyz[:, 0] < -1.0
    right = xyz[:, 0] > 1.0
    assert (rgb[left] == (33, 102, 172)).all() and (rgb[right] == (178, 24, 43)).all()
    _, none, _ = cloud_arrays(res, 100_000, "change")  # no change map: black
    assert not none.any()
