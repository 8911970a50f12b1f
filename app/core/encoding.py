"""Arrays as file bytes: NPY and PNG (8/16-bit grey, or RGB), the one home of both encoders."""

from __future__ import annotations

import io
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt


def npy_bytes(array: npt.ArrayLike) -> bytes:
    """``array`` as ``.npy`` file bytes (no pickling: plain numeric arrays only)."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def png_bytes(image: npt.NDArray[Any], *, rgb: bool = False, compression: int = 1,
              filter_none: bool = False) -> bytes:
    """``image`` as PNG file bytes.

    Args:
        image: (H, W) uint8/uint16 grey, or (H, W, 3) uint8 colour.
        rgb: the colour channels are in R, G, B order (default: OpenCV's B, G, R).
        compression: zlib level 0–9 (1: fast, the default for live images).
        filter_none: no per-row PNG prediction filter: a third of the CPU, as small for
            images of flat colour (reason maps), larger for photographs.
    """
    img = np.asarray(image)
    if rgb:
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image: rgb needs an (H, W, 3) array, got shape {img.shape}")
        img = img[..., ::-1]
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    if filter_none:
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), params)
    if not ok:
        raise OSError("PNG encoding failed")
    return bytes(buf.tobytes())
