"""NPY and PNG bytes decode back to the same arrays."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest

from app.core.encoding import npy_bytes, png_bytes


def test_npy_round_trip_keeps_nan_and_dtype():
    a = np.array([[1.5, np.nan], [-2.0, 3.25]], np.float32)
    b = np.load(io.BytesIO(npy_bytes(a)), allow_pickle=False)
    assert b.dtype == np.float32 and np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_grey_round_trip(dtype):
    a = (np.arange(12 * 7).reshape(12, 7) * 97 % np.iinfo(dtype).max).astype(dtype)
    b = cv2.imdecode(np.frombuffer(png_bytes(a), np.uint8), cv2.IMREAD_UNCHANGED)
    assert b.dtype == dtype and np.array_equal(a, b)


def test_png_rgb_order():
    a = np.zeros((2, 3, 3), np.uint8)
    a[..., 0] = 200  # red
    bgr = cv2.imdecode(np.frombuffer(png_bytes(a, rgb=True), np.uint8), cv2.IMREAD_COLOR)
    assert (bgr[..., 2] == 200).all() and (bgr[..., :2] == 0).all()
    with pytest.raises(ValueError, match="image"):
        png_bytes(np.zeros((2, 3), np.uint8), rgb=True)
