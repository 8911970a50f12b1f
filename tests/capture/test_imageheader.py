"""Frame sizes from PNG, TIFF and .npy.zst headers, checked against limits before anything is
decoded."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
import zstandard

from app.capture.captureset import zstd_frame_bytes
from app.capture.imageheader import FrameLimits, ImageHeader, check_frame_headers, read_image_header
from tests.helpers.hostile import zero_png


@pytest.mark.parametrize(
    "shape, dtype, channels",
    [
        ((12, 20), np.uint8, 1),
        ((12, 20), np.uint16, 1),
        ((12, 20, 3), np.uint8, 3),
        ((12, 20, 4), np.uint16, 4),
    ],
)
def test_png_and_tiff_headers_match_what_opencv_decodes(
    tmp_path: Path, shape: tuple[int, ...], dtype: type, channels: int
) -> None:
    img = np.zeros(shape, dtype)
    for ext in ("png", "tiff"):
        path = tmp_path / f"f.{ext}"
        if ext == "png":
            cv2.imwrite(str(path), img)
        else:
            tifffile.imwrite(path, img, photometric="rgb" if channels >= 3 else "minisblack")
        head = read_image_header(path)
        decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert (head.width, head.height, head.format) == (20, 12, ext)
        assert head.decoded_bytes == decoded.nbytes, (ext, head, decoded.shape, decoded.dtype)


def test_a_bomb_header_is_read_without_decoding(tmp_path: Path) -> None:
    path = tmp_path / "bomb.png"
    path.write_bytes(zero_png(12000, 12000))  # 144 MP; decoding would take 144 MB
    head = read_image_header(path)
    assert (head.width, head.height, head.decoded_bytes) == (12000, 12000, 144_000_000)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "not a PNG, TIFF or .npy.zst frame"),
        (b"GIF89a" + bytes(40), "not a PNG"),
        (b"\x89PNG\r\n\x1a\n" + bytes(8), "truncated PNG"),
        (b"II*\x00" + bytes(4), "invalid TIFF"),
    ],
)
def test_other_files_are_refused_naming_them(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "frame_00.png"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=f"^frame_00.png: {message}"):
        read_image_header(path)


def test_limits_name_the_first_frame_that_breaks_them() -> None:
    small = ImageHeader(640, 480, 1, 1, "png")
    names = ["a.png", "b.png", "c.png"]
    check_frame_headers([small] * 3, names, FrameLimits(frame_size=(640, 480)))
    with pytest.raises(
        ValueError, match=r"^a.png: image size 640x480 does not match the calibration's 320x240"
    ):
        check_frame_headers([small] * 3, names, FrameLimits(frame_size=(320, 240)))
    with pytest.raises(
        ValueError, match=r"^b.png: image size 320x240 differs from the first frame's 640x480"
    ):
        check_frame_headers(
            [small, ImageHeader(320, 240, 1, 1, "png"), small], names, FrameLimits()
        )
    with pytest.raises(ValueError, match=r"^a.png: 640x480 is 307200 pixels, more than the 1000"):
        check_frame_headers([small] * 3, names, FrameLimits(max_frame_pixels=1000))
    with pytest.raises(ValueError, match=r"^c.png: the frames up to here decode to 921600 bytes"):
        check_frame_headers([small] * 3, names, FrameLimits(max_set_bytes=700_000))


@pytest.mark.parametrize(("dtype", "shape"), [(np.uint8, (24, 32)), (np.uint16, (1032, 1384))])
def test_npy_zst_frame_header_is_read_without_decompressing_the_pixels(tmp_path, dtype, shape):
    path = tmp_path / "frame_00.npy.zst"
    path.write_bytes(zstd_frame_bytes(np.arange(np.prod(shape)).reshape(shape).astype(dtype)))
    header = read_image_header(path)
    assert (header.width, header.height, header.channels) == (shape[1], shape[0], 1)
    assert header.bytes_per_sample == np.dtype(dtype).itemsize and header.format == "npy.zst"


def test_npy_zst_frame_of_floats_is_refused_from_its_header(tmp_path):
    buf = io.BytesIO()
    np.save(buf, np.zeros((8, 8), np.float32))
    path = tmp_path / "frame_00.npy.zst"
    path.write_bytes(zstandard.ZstdCompressor().compress(buf.getvalue()))
    with pytest.raises(ValueError, match="frame_00.npy.zst: expected an \\(H, W\\) uint8/uint16"):
        read_image_header(path)
