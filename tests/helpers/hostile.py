"""Hostile inputs built small: PNG decompression bombs and capture sets, without big arrays."""

from __future__ import annotations

import io
import json
import struct
import zipfile
import zlib

from app.core.schedule import PatternSchedule


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def zero_png(width: int, height: int) -> bytes:
    """An all-zero 8-bit grey PNG, compressed row by row (never the whole image in memory)."""
    comp = zlib.compressobj(9)
    row = b"\0" * (width + 1)  # filter byte + pixels
    idat = b"".join(comp.compress(row) for _ in range(height)) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


def capture_json(n_frames: int = 16) -> bytes:
    schedule = PatternSchedule()
    assert schedule.n_frames == n_frames
    return json.dumps(
        {
            "format": "fringescope.capture/1",
            "pattern": schedule.to_dict(),
            "exposure_ms": 20.0,
            "led": "green",
            "frames": [f"frame_{i:02d}.png" for i in range(n_frames)],
        }
    ).encode()


def png_bomb_zip(width: int = 8000, height: int = 8000, n_frames: int = 16) -> bytes:
    """A zip of ``n_frames`` all-zero PNGs (8000 × 8000: ~1 MB that decodes to ~1 GB)."""
    png = zero_png(width, height)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        zf.writestr("set/capture.json", capture_json(n_frames))
        for i in range(n_frames):
            zf.writestr(f"set/frame_{i:02d}.png", png)
    return buf.getvalue()
