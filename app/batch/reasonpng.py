"""``reason.png`` written as an indexed (palette) PNG: the image of
:func:`app.recon.colormap.reason_png`, pixel for pixel, at a fraction of its cost.

A reason map has a handful of colours, so a PNG reader (OpenCV, Pillow, a browser) gets
the same RGB image from a one-byte-per-pixel palette image: a third of the bytes to build
and to deflate. The map's pixels are its codes looked up in a code → palette index table;
only the legend strip below it is drawn in colour (as :mod:`app.recon.colormap` draws it)
and turned into indices. When the image would need more than 256 colours (anti-aliased
legend text can use many greys), the RGB PNG of :func:`~app.recon.colormap.reason_png` is
written instead: the same pixels either way.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import numpy.typing as npt

from app.recon.colormap import REASON_COLORS, reason_png

#: the colour of a code that is not a :class:`~app.core.reasons.Reason` (RGB)
UNKNOWN_COLOR = (255, 0, 255)
LEGEND_ROW_PX = 18
LEGEND_GAP_PX = 6
MIN_WIDTH_PX = 230
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def palette_png_bytes(rows: npt.NDArray[np.uint8], palette: npt.NDArray[np.uint8],
                      level: int = 1) -> bytes:
    """An 8-bit indexed PNG from its filtered scanlines.

    Args:
        rows: (H, 1 + W) uint8, C-contiguous: per row the PNG filter byte (0: none) and
            the W palette indices.
        palette: (N, 3) uint8 RGB, 1 <= N <= 256; every index in ``rows`` must be < N.
        level: zlib level 0-9.

    Returns:
        The PNG file's bytes.
    """
    if rows.dtype != np.uint8 or rows.ndim != 2 or rows.shape[1] < 2 or rows.shape[0] < 1:
        raise ValueError(f"rows: expected (H, 1 + W) uint8, got {rows.dtype} {rows.shape}")
    if palette.dtype != np.uint8 or palette.ndim != 2 or palette.shape[1] != 3 \
            or not 1 <= palette.shape[0] <= 256:
        raise ValueError(f"palette: expected (N <= 256, 3) uint8, got {palette.dtype} "
                         f"{palette.shape}")
    height, width = rows.shape[0], rows.shape[1] - 1
    header = struct.pack(">IIBBBBB", width, height, 8, 3, 0, 0, 0)  # 8 bit, indexed
    # run-length matching only: reason maps are runs of one index, and it is the fastest
    packer = zlib.compressobj(level, zlib.DEFLATED, zlib.MAX_WBITS, 9, zlib.Z_RLE)
    data = packer.compress(np.ascontiguousarray(rows).data) + packer.flush()
    return b"".join((PNG_SIGNATURE, _chunk(b"IHDR", header), _chunk(b"PLTE", palette.tobytes()),
                     _chunk(b"IDAT", data), _chunk(b"IEND", b"")))


def _legend_bgr(counts: npt.NDArray[np.int64], total: int,
                width: int) -> npt.NDArray[np.uint8]:
    """The legend strip below the map, B, G, R, as :func:`reason_png` draws it: its left
    part as wide as the drawing needs (at most ``width``); the rest of the strip is white."""
    labels = [f"{int(code)} {code.name.lower()} {100.0 * float(counts[int(code)]) / total:.1f}%"
              for code in REASON_COLORS]
    # the text's advance plus a margin for its anti-aliased edge
    drawn = 22 + max(cv2.getTextSize(t, _FONT, 0.4, 1)[0][0] for t in labels) + 8
    strip = np.full((LEGEND_GAP_PX + LEGEND_ROW_PX * len(REASON_COLORS), min(width, drawn), 3),
                    255, np.uint8)
    for i, (label, color) in enumerate(zip(labels, REASON_COLORS.values(), strict=True)):
        y = LEGEND_GAP_PX + i * LEGEND_ROW_PX
        bgr = color[::-1]
        cv2.rectangle(strip, (4, y + 3), (16, y + 14), bgr, -1)
        cv2.rectangle(strip, (4, y + 3), (16, y + 14), (0, 0, 0), 1)
        cv2.putText(strip, label, (22, y + 13), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return strip


def reason_png_indexed(reason: npt.ArrayLike, level: int = 1) -> bytes:
    """:func:`app.recon.colormap.reason_png`'s image (map and legend) as a palette PNG.

    Args:
        reason: (H, W) integer reason codes (:class:`~app.core.reasons.Reason`; other
            codes are drawn magenta).
        level: zlib level 0-9.

    Returns:
        PNG bytes that decode to the same RGB pixels as ``reason_png(reason)``.
    """
    r = np.asarray(reason)
    if r.ndim != 2 or not np.issubdtype(r.dtype, np.integer):
        raise ValueError(f"reason: expected an (H, W) integer array, got {r.dtype} {r.shape}")
    height, width = r.shape
    codes = np.clip(r, 0, 255).astype(np.uint8, copy=False)
    counts = np.zeros(256, np.int64)
    for code in map(int, REASON_COLORS):  # a pass per code: cheaper than a 256-bin bincount
        counts[code] = np.count_nonzero(r == code)  # (an enum member would compare slowly)
    known = int(counts.sum())
    total = max(r.size, 1)
    canvas_w = max(width, MIN_WIDTH_PX)
    strip = _legend_bgr(counts, total, canvas_w)

    colours: dict[tuple[int, int, int], int] = {}  # RGB -> palette index, in order of use

    def index_of(rgb: tuple[int, int, int]) -> int:
        return colours.setdefault(rgb, len(colours))

    # the codes' colours first, at their codes' indices when the codes are 0..n-1 (then a
    # uint8 map is its own index image), magenta for unknown codes after them
    for color in REASON_COLORS.values():
        index_of(color)
    code_index = np.full(256, index_of(UNKNOWN_COLOR) if known < r.size else 0, np.uint8)
    for code, color in REASON_COLORS.items():
        code_index[int(code)] = colours[color]
    as_is = (r.dtype == np.uint8 and known == r.size
             and all(code_index[int(c)] == int(c) for c in REASON_COLORS))
    # the legend: greys (text on white) by grey level, the swatches' colours one by one
    grey = (strip[..., 0] == strip[..., 1]) & (strip[..., 1] == strip[..., 2])
    grey_index = np.zeros(256, np.uint8)
    levels = np.flatnonzero(np.bincount(strip[..., 0][grey], minlength=256))
    coloured = strip[~grey]
    keys = (coloured[:, 2].astype(np.uint32) << 16) | (coloured[:, 1].astype(np.uint32) << 8) \
        | coloured[:, 0]
    other, inverse = np.unique(keys, return_inverse=True)
    if len(set(colours) | {(v, v, v) for v in levels.tolist()}
           | {(k >> 16, (k >> 8) & 255, k & 255) for k in other.tolist()}) > 256:
        return reason_png(r)
    if width < canvas_w or strip.shape[1] < canvas_w:  # white right of the map or legend
        index_of((255, 255, 255))
    for v in levels.tolist():
        grey_index[v] = index_of((v, v, v))
    other_index = np.array([index_of((k >> 16, (k >> 8) & 255, k & 255)) for k in other.tolist()],
                           np.uint8)

    rows = np.zeros((height + strip.shape[0], 1 + canvas_w), np.uint8)  # filter byte 0: none
    if as_is:
        rows[:height, 1:1 + width] = r
    else:
        np.take(code_index, codes, out=rows[:height, 1:1 + width], mode="wrap")
    if width < canvas_w:
        rows[:height, 1 + width:] = colours[(255, 255, 255)]
    legend = rows[height:, 1:1 + strip.shape[1]]
    if strip.shape[1] < canvas_w:
        rows[height:, 1 + strip.shape[1]:] = colours[(255, 255, 255)]
    np.take(grey_index, strip[..., 0], out=legend, mode="wrap")
    legend[~grey] = other_index[inverse.ravel()]
    palette = np.array(list(colours), np.uint8).reshape(-1, 3)
    return palette_png_bytes(rows, palette, level)
