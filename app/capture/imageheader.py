"""Frame sizes read from PNG, TIFF and ``.npy.zst`` headers: an upload is bounded before any
pixel is decoded.

A PNG of 8000 × 8000 zeros is ~60 kB on the wire and 64 MB once decoded: a set of such
frames (a decompression bomb) is refused from its headers — size against the calibration's,
pixels and decoded bytes against a stated budget — before OpenCV decodes anything.
"""

from __future__ import annotations

import ast
import io
import struct
from dataclasses import dataclass
from pathlib import Path

import zstandard

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
ZSTD_SIGNATURE = b"\x28\xb5\x2f\xfd"
NPY_SIGNATURE = b"\x93NUMPY"
#: channels OpenCV decodes per PNG colour type (a palette becomes BGR)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}

#: the largest frame an upload may hold without a calibration to compare with, pixels
MAX_FRAME_PIXELS = 4096 * 4096
#: the most a whole uploaded set may take once decoded, bytes (with the upload body and the
#: reconstruction's own arrays this bounds the server's memory growth per upload)
MAX_SET_DECODED_BYTES = 256 * 1024 * 1024


@dataclass(frozen=True)
class ImageHeader:
    """What decoding one image would produce.

    Attributes:
        width, height: pixels.
        channels: planes OpenCV decodes (1 grey, 3 BGR, 4 BGRA, …).
        bytes_per_sample: 1 (8-bit and less) or 2 (16-bit); 4/8 for float TIFFs.
        format: ``"png"`` or ``"tiff"``.
    """

    width: int
    height: int
    channels: int
    bytes_per_sample: int
    format: str

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the decoded array."""
        return self.pixels * self.channels * self.bytes_per_sample


@dataclass(frozen=True)
class FrameLimits:
    """Bounds checked on headers before a set's frames are decoded.

    Attributes:
        frame_size: (width, height) every frame must have (the calibration's), or None.
        max_frame_pixels: the most pixels one frame may have.
        max_set_bytes: the most the whole set may take once decoded, bytes.
    """

    frame_size: tuple[int, int] | None = None
    max_frame_pixels: int = MAX_FRAME_PIXELS
    max_set_bytes: int = MAX_SET_DECODED_BYTES


def read_image_header(path: str | Path) -> ImageHeader:
    """The header of a PNG, TIFF or ``.npy.zst`` frame; ``ValueError`` naming the file otherwise.

    Reads the PNG IHDR chunk (first 33 bytes), the TIFF's first page directory or the first
    bytes a zstd frame decompresses to (the ``.npy`` header); never decodes pixel data.
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(33)
            if head.startswith(PNG_SIGNATURE):
                return _png_header(head, p.name)
            if head[:4] in TIFF_SIGNATURES:
                fh.seek(0)
                return _tiff_header(fh, p.name)
            if head.startswith(ZSTD_SIGNATURE):
                fh.seek(0)
                return _npy_zst_header(fh, p.name)
    except OSError as exc:
        raise ValueError(f"{p.name}: missing or unreadable ({exc.strerror or exc})") from None
    raise ValueError(f"{p.name}: not a PNG, TIFF or .npy.zst frame")


def _png_header(head: bytes, name: str) -> ImageHeader:
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise ValueError(f"{name}: truncated PNG header")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16) or not (width and height):
        raise ValueError(
            f"{name}: invalid PNG header ({width}x{height}, colour type {colour}, "
            f"bit depth {depth})"
        )
    return ImageHeader(width, height, _PNG_CHANNELS[colour], 2 if depth == 16 else 1, "png")


def _tiff_header(fh: io.BufferedReader, name: str) -> ImageHeader:
    import tifffile

    try:
        with tifffile.TiffFile(fh) as tif:
            page = tif.pages.first
            shape = tuple(int(n) for n in page.shape)
            itemsize = int(page.dtype.itemsize) if page.dtype is not None else 1
    except Exception as exc:  # tifffile raises many types for a malformed file
        raise ValueError(f"{name}: invalid TIFF header ({type(exc).__name__})") from None
    if len(shape) == 2:
        (height, width), channels = shape, 1
    elif len(shape) == 3 and shape[2] <= 4:
        height, width, channels = shape
    else:
        raise ValueError(f"{name}: TIFF page of shape {shape}: expected one grey or colour image")
    return ImageHeader(width, height, channels, itemsize, "tiff")


def check_frame_headers(headers: list[ImageHeader], names: list[str], limits: FrameLimits) -> None:
    """``ValueError`` naming the first frame that breaks ``limits`` or differs from the first.

    Args:
        headers: one per frame, in order.
        names: the frames' file names (for the messages).
        limits: the bounds to check.
    """
    total = 0
    for head, name in zip(headers, names, strict=True):
        size = (head.width, head.height)
        if limits.frame_size is not None and size != tuple(limits.frame_size):
            w, h = limits.frame_size
            raise ValueError(
                f"{name}: image size {head.width}x{head.height} does not match the "
                f"calibration's {w}x{h}"
            )
        if head.pixels > limits.max_frame_pixels:
            raise ValueError(
                f"{name}: {head.width}x{head.height} is {head.pixels} pixels, more than "
                f"the {limits.max_frame_pixels} a frame may have"
            )
        first = headers[0]
        if size != (first.width, first.height):
            raise ValueError(
                f"{name}: image size {head.width}x{head.height} differs from the first "
                f"frame's {first.width}x{first.height}"
            )
        total += head.decoded_bytes
        if total > limits.max_set_bytes:
            raise ValueError(
                f"{name}: the frames up to here decode to {total} bytes, more than the "
                f"{limits.max_set_bytes}-byte budget of a set"
            )


def _npy_zst_header(fh: io.BufferedReader, name: str) -> ImageHeader:
    """The ``.npy`` header at the start of a zstd-compressed frame (its first 256 bytes only)."""
    try:
        with zstandard.ZstdDecompressor().stream_reader(fh) as reader:
            head = reader.read(256)
    except zstandard.ZstdError:
        raise ValueError(f"{name}: not a zstd frame") from None
    if not head.startswith(NPY_SIGNATURE) or len(head) < 10:
        raise ValueError(f"{name}: not an .npy.zst frame")
    major = head[6]
    n_len, start = (struct.unpack("<H", head[8:10])[0], 10) if major == 1 else (
        struct.unpack("<I", head[8:12])[0], 12)
    try:
        meta = ast.literal_eval(head[start:start + n_len].decode("latin1"))
        shape, descr = tuple(meta["shape"]), str(meta["descr"])
    except (ValueError, SyntaxError, KeyError, TypeError, UnicodeDecodeError):
        raise ValueError(f"{name}: unreadable .npy header") from None
    if len(shape) != 2 or descr not in ("|u1", "<u2") or not all(
            isinstance(d, int) and d > 0 for d in shape):
        raise ValueError(f"{name}: expected an (H, W) uint8/uint16 frame, got {shape} {descr}")
    return ImageHeader(shape[1], shape[0], 1, 1 if descr == "|u1" else 2, "npy.zst")
