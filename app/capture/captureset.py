"""Capture sets on disk: ``capture.json`` plus one file per fringe frame (DESIGN.md).

A frame file is a PNG (8/16-bit grey or colour), or, for recordings written at the
camera's rate, ``frame_XX.npy.zst``: a zstd-compressed ``.npy`` of the frame's
horizontal differences (``d[:, 0] = f[:, 0]``, ``d[:, 1:] = f[:, 1:] - f[:, :-1]``, unsigned
wraparound), so ``f = cumsum(d, axis=1)`` in the frame's dtype. On a 1384 × 1032 8-bit
tissue frame it is as small as PNG at level 1 for about a fifth of the CPU
(``benchmarks/bench_recording.py``). The reader takes either, listed in ``"frames"``.
"""

from __future__ import annotations

import io
import json
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import zstandard

from app.atomic import atomic_directory
from app.capture.imageheader import FrameLimits, check_frame_headers, read_image_header
from app.core.encoding import png_bytes
from app.core.jsonlimits import check_json_depth
from app.core.limits import (
    CAPTURE_BIT_DEPTHS,
    CHANNELS,
    DEFAULT_EXPOSURE_MS,
    DEFAULT_LED,
    check_led,
    full_scale,
)
from app.core.schedule import PatternSchedule

FORMAT = "fringescope.capture/1"
#: the largest capture.json read, bytes (a real one is well under 10 kB)
MAX_META_BYTES = 1024 * 1024
#: how frames are stored: ``png`` (level 1) or ``zstd`` (row differences, zstd level 1)
FRAME_CODECS: tuple[str, ...] = ("png", "zstd")
ZSTD_SUFFIX = ".npy.zst"
#: largest decompressed frame file accepted, bytes: a 16-bit 4096 x 4096 frame and its
#: ``.npy`` header (an upload's small file must not decompress to more)
MAX_FRAME_BYTES = 32 * 2**20 + 4096
ZSTD_LEVEL = 1  # level 1: the noise in fringe frames makes higher levels cost CPU for ~10 %
_BGR_INDEX = {"blue": 0, "green": 1, "red": 2}


@dataclass
class CaptureSet:
    """One depth map's worth of fringe frames.

    Attributes:
        frames: (F, H, W) uint8 or uint16, frequency-major, shift-minor.
        schedule: the pattern schedule the frames were taken with.
        exposure_ms: camera exposure, ms.
        led: projector LED colour.
        extra: unknown keys of ``capture.json`` (kept, ignored).
        bit_depth: significant bits of the sensor codes (8, 10, 12, 14, 16); None → the
            frames' full range. Saturation and modulation thresholds follow it.
        channel: for colour frames on disk, the channel decoded (``red``, ``green``,
            ``blue`` or ``luminance``); None for mono frames.
    """

    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
    schedule: PatternSchedule = field(default_factory=PatternSchedule)
    exposure_ms: float = DEFAULT_EXPOSURE_MS
    led: str = DEFAULT_LED
    extra: dict[str, Any] = field(default_factory=dict)
    bit_depth: int | None = None
    channel: str | None = None

    def __post_init__(self) -> None:
        validate_frames(self.frames, self.schedule)
        if not (math.isfinite(self.exposure_ms) and self.exposure_ms > 0):
            raise ValueError(f"exposure_ms: must be positive, got {self.exposure_ms}")
        check_led(self.led)
        if self.channel is not None and self.channel not in CHANNELS:
            raise ValueError(f"channel: must be one of {CHANNELS}, got {self.channel!r}")
        if self.bit_depth is not None:
            check_bit_depth(self.frames, self.bit_depth)

    @property
    def max_code(self) -> int:
        """Saturation code: 2**bit_depth − 1, or the frames' full range (255 / 65535)."""
        if self.bit_depth is not None:
            return full_scale(self.bit_depth)
        return 255 if self.frames.dtype == np.uint8 else 65535


def check_bit_depth(frames: npt.NDArray[Any], bit_depth: Any) -> None:
    """``ValueError`` naming ``bit_depth`` unless it is allowed and no frame value exceeds it."""
    if isinstance(bit_depth, bool) or bit_depth not in CAPTURE_BIT_DEPTHS:
        raise ValueError(f"bit_depth: must be one of {CAPTURE_BIT_DEPTHS}, got {bit_depth!r}")
    if bit_depth > 8 and frames.dtype == np.uint8:
        raise ValueError(f"bit_depth: {bit_depth} bits need 16-bit frames, the frames are 8-bit")
    top = int(frames.max())
    if top > full_scale(bit_depth):
        raise ValueError(f"bit_depth: frames hold values up to {top}, above the {bit_depth}-bit "
                         f"maximum {full_scale(bit_depth)}")


def to_channel(image: npt.NDArray[Any], channel: str) -> npt.NDArray[Any]:
    """One channel of a (H, W, 3|4) BGR(A) image as OpenCV reads it, same dtype.

    ``luminance`` is Rec. 601 luma (``cv2.cvtColor``), the others pick a plane.
    """
    if channel not in CHANNELS:
        raise ValueError(f"channel: must be one of {CHANNELS}, got {channel!r}")
    if channel == "luminance":
        return cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(image[..., _BGR_INDEX[channel]])


def validate_frames(frames: Any, schedule: PatternSchedule) -> None:
    """Raise ``ValueError`` naming ``frames`` unless it is a (F, H, W) uint8/uint16 stack for
    ``schedule``."""
    if not isinstance(frames, np.ndarray):
        raise ValueError("frames: expected a numpy array")
    if frames.ndim != 3:
        raise ValueError(f"frames: expected shape (F, H, W), got {frames.shape}")
    if frames.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"frames: dtype must be uint8 or uint16, got {frames.dtype}")
    if frames.shape[0] != schedule.n_frames:
        raise ValueError(
            f"frames: schedule needs {schedule.n_frames} frames, got {frames.shape[0]}")


def _read_meta(meta_path: Path) -> Any:
    """``capture.json`` parsed, its size and depth checked first; ``ValueError`` names it."""
    try:
        with open(meta_path, "rb") as fh:
            raw = fh.read(MAX_META_BYTES + 1)
    except FileNotFoundError:
        raise ValueError(f"{meta_path}: capture-set metadata not found") from None
    except OSError as exc:
        raise ValueError(f"{meta_path}: unreadable capture-set metadata ({exc})") from None
    if len(raw) > MAX_META_BYTES:
        raise ValueError(f"{meta_path}: larger than {MAX_META_BYTES} bytes")
    check_json_depth(raw, str(meta_path))
    try:
        return json.loads(raw)
    except ValueError as exc:  # not JSON, not UTF-8, an integer of more than 4300 digits
        raise ValueError(f"{meta_path}: unreadable capture-set metadata ({exc})") from None


def frame_names(n: int, codec: str = "png") -> list[str]:
    """The file names of ``n`` frames stored with ``codec`` (see :data:`FRAME_CODECS`)."""
    if codec not in FRAME_CODECS:
        raise ValueError(f"codec: must be one of {FRAME_CODECS}, got {codec!r}")
    suffix = ".png" if codec == "png" else ZSTD_SUFFIX
    return [f"frame_{i:02d}{suffix}" for i in range(n)]


def zstd_frame_bytes(frame: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]) -> bytes:
    """One (H, W) uint8/uint16 frame as ``.npy.zst`` bytes (row differences, zstd level 1)."""
    if frame.ndim != 2 or frame.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"frame: expected (H, W) uint8/uint16, got {frame.shape} {frame.dtype}")
    diff = np.empty_like(frame)
    diff[:, 0] = frame[:, 0]
    np.subtract(frame[:, 1:], frame[:, :-1], out=diff[:, 1:])  # unsigned: wraps, undone by cumsum
    buf = io.BytesIO()
    np.save(buf, diff, allow_pickle=False)
    return bytes(zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(buf.getvalue()))


def read_zstd_frame(path: Path, out: npt.NDArray[Any] | None = None) -> npt.NDArray[Any]:
    """A frame written by :func:`zstd_frame_bytes`; ``ValueError`` naming ``path`` if not one.

    ``out``: an (H, W) array to decode into when the frame has its shape and dtype (a
    reader filling a preallocated stack); a frame of another shape or dtype comes back as
    a new array, untouched ``out``, for the caller to report.
    """
    try:
        data = path.read_bytes()
    except OSError:
        raise ValueError(f"{path}: missing or not a readable frame") from None
    try:
        size = zstandard.frame_content_size(data)
    except zstandard.ZstdError:
        raise ValueError(f"{path}: not a zstd frame") from None
    if size < 0 or size > MAX_FRAME_BYTES:  # a declared size bounds memory before decompressing
        raise ValueError(f"{path}: decompressed size {size} outside 0..{MAX_FRAME_BYTES} bytes")
    try:
        raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=MAX_FRAME_BYTES)
        diff = _npy_view(raw)
    except (zstandard.ZstdError, ValueError, OSError, EOFError) as exc:
        raise ValueError(f"{path}: unreadable frame ({exc})") from None
    if diff.ndim != 2 or diff.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: expected an (H, W) uint8/uint16 frame, got {diff.shape} "
                         f"{diff.dtype}")
    if out is None or out.shape != diff.shape or out.dtype != diff.dtype:
        out = np.empty(diff.shape, diff.dtype)
    _undiff_rows()(diff, out)
    return out


_UNDIFF: Callable[[npt.NDArray[Any], npt.NDArray[Any]], None] | None = None


def _undiff_rows() -> Callable[[npt.NDArray[Any], npt.NDArray[Any]], None]:
    """The compiled ``undiff(diff, out)``: ``out[i, j] = diff[i, 0] + … + diff[i, j]`` modulo
    the (H, W) uint8/uint16 arrays' range, the inverse of :func:`zstd_frame_bytes`'s row
    differences. One pass in numba (compiled on first use, cached): 0.34 ms per 1384 × 1032
    uint8 frame, against 0.77 ms for numpy's uint16 running sum and its copy."""
    global _UNDIFF
    if _UNDIFF is None:
        from numba import njit

        @njit(cache=True, nogil=True)
        def undiff(diff: npt.NDArray[Any], out: npt.NDArray[Any]) -> None:  # pragma: no cover
            for i in range(diff.shape[0]):
                acc = 0
                for j in range(diff.shape[1]):
                    acc += diff[i, j]
                    out[i, j] = acc  # stored modulo 2^8 / 2^16: the writer's differences wrap
        _UNDIFF = undiff
    return _UNDIFF


def _npy_view(raw: bytes) -> npt.NDArray[Any]:
    """The array of ``.npy`` bytes as a read-only view on them (no copy); C order only."""
    from numpy.lib import format as npy_format

    head = io.BytesIO(raw)
    version = npy_format.read_magic(head)
    if version == (1, 0):
        shape, fortran, dtype = npy_format.read_array_header_1_0(head)
    elif version == (2, 0):
        shape, fortran, dtype = npy_format.read_array_header_2_0(head)
    else:
        raise ValueError(f"unsupported .npy version {version}")
    if fortran or dtype.hasobject:
        raise ValueError("expected a C-ordered numeric array")
    count = math.prod(shape)
    if head.tell() + count * dtype.itemsize != len(raw):
        raise ValueError(f"{len(raw) - head.tell()} data bytes for shape {shape} {dtype}")
    return np.frombuffer(raw, dtype, count, head.tell()).reshape(shape)


def encode_frames(frames: npt.NDArray[Any], codec: str = "png", workers: int = 1,
                  encode_cpu_s: list[float] | None = None) -> list[bytes]:
    """Each (H, W) frame of ``frames`` as file bytes of ``codec`` (see :data:`FRAME_CODECS`).

    ``workers`` threads encode them (both encoders release the GIL); each frame's encoding
    CPU time (s) is appended to ``encode_cpu_s`` when given.
    """
    if codec not in FRAME_CODECS:
        raise ValueError(f"codec: must be one of {FRAME_CODECS}, got {codec!r}")
    encoder = png_bytes if codec == "png" else zstd_frame_bytes

    def encode(frame: npt.NDArray[Any]) -> bytes:
        t0 = time.thread_time()
        data = encoder(frame)
        if encode_cpu_s is not None:
            encode_cpu_s.append(time.thread_time() - t0)
        return data

    if workers > 1:
        with ThreadPoolExecutor(workers, thread_name_prefix="fringescope-encode") as pool:
            return list(pool.map(encode, frames))
    return [encode(frame) for frame in frames]


def write_capture_set(
    path: str | os.PathLike[str], capture: CaptureSet, *, overwrite: bool = False,
    extra_files: dict[str, bytes] | None = None, codec: str = "png",
    encoded: list[bytes] | None = None,
) -> Path:
    """Write ``capture`` as a capture-set folder, atomically (it appears whole or not at all).

    ``extra_files`` (name → bytes) are written into the same folder, e.g. depth results.
    ``codec`` stores the frames as PNG or as ``.npy.zst`` (see the module docstring);
    ``encoded``: the frames already encoded with it (:func:`encode_frames`), in order.
    """
    names = frame_names(capture.frames.shape[0], codec)
    if encoded is not None and len(encoded) != len(names):
        raise ValueError(f"encoded: {len(encoded)} frames for a set of {len(names)}")
    meta = {
        **capture.extra,
        "format": FORMAT,
        "pattern": capture.schedule.to_dict(),
        "exposure_ms": float(capture.exposure_ms),
        "led": capture.led,
        "frames": names,
        **({"bit_depth": capture.bit_depth} if capture.bit_depth is not None else {}),
    }
    with atomic_directory(path, overwrite=overwrite) as tmp:
        if encoded is None:
            encoded = encode_frames(capture.frames, codec)
        for name, data in zip(names, encoded, strict=True):
            (tmp / name).write_bytes(data)
        for name, data in (extra_files or {}).items():
            (tmp / name).write_bytes(data)
        (tmp / "capture.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return Path(path)


def read_capture_set(
    path: str | os.PathLike[str], *, limits: FrameLimits | None = None
) -> CaptureSet:
    """Read a capture-set folder; ``ValueError`` naming the offending file on any problem.

    ``capture.json`` is refused when larger than :data:`MAX_META_BYTES` or nested deeper
    than a capture set needs (checked before parsing). With ``limits`` (uploads) the frames must be
    PNG or TIFF and their headers are checked against ``limits`` before any is decoded.
    """
    folder = Path(path)
    meta_path = folder / "capture.json"
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a capture-set folder")
    meta = _read_meta(meta_path)
    if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object")
    if meta.get("format") != FORMAT:
        raise ValueError(f"{meta_path}: unsupported format {meta.get('format')!r} "
                         f"(expected {FORMAT!r})")
    for key in ("pattern", "frames"):
        if key not in meta:
            raise ValueError(f"{meta_path}: missing key {key!r}")
    try:
        schedule = PatternSchedule.from_dict(meta["pattern"])
    except ValueError as exc:
        raise ValueError(f"{meta_path}: {exc}") from None
    channel = meta.get("channel")
    if channel is not None and channel not in CHANNELS:
        raise ValueError(f"{meta_path}: channel: must be one of {CHANNELS}, got {channel!r}")
    bit_depth = meta.get("bit_depth")
    if bit_depth is not None and (isinstance(bit_depth, bool)
                                  or bit_depth not in CAPTURE_BIT_DEPTHS):
        raise ValueError(f"{meta_path}: bit_depth: must be one of {CAPTURE_BIT_DEPTHS}, "
                         f"got {bit_depth!r}")
    led = meta.get("led", DEFAULT_LED)
    names = meta["frames"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{meta_path}: 'frames' must be a list of file names")
    if len(names) != schedule.n_frames:
        raise ValueError(
            f"{meta_path}: schedule needs {schedule.n_frames} frames, lists {len(names)}")
    for name in names:
        if Path(name).name != name or len(name) > 255:
            raise ValueError(f"{meta_path}: frame name {name[:40]!r} must be a plain file name "
                             "(at most 255 characters)")
    if limits is not None:
        try:
            check_frame_headers([read_image_header(folder / n) for n in names], names, limits)
        except ValueError as exc:
            raise ValueError(f"{folder}/{exc}") from None
    # the first frame fixes the stack's shape and dtype; the others are decoded into it
    # (a zstd frame in place), so reading holds one set and at most one frame besides
    stack: npt.NDArray[Any] | None = None
    for i, name in enumerate(names):
        fpath = folder / name
        img = (read_zstd_frame(fpath, None if stack is None else stack[i])
               if name.endswith(ZSTD_SUFFIX) else cv2.imread(str(fpath), cv2.IMREAD_UNCHANGED))
        if img is None:
            raise ValueError(f"{fpath}: missing or not a readable image")
        if img.ndim == 3 and img.shape[2] in (3, 4):
            img = to_channel(img, channel or (led if led in _BGR_INDEX else "luminance"))
            channel = channel or (led if led in _BGR_INDEX else "luminance")
        elif img.ndim != 2:
            raise ValueError(f"{fpath}: expected a grey or colour image, got shape {img.shape}")
        if img.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"{fpath}: expected 8- or 16-bit pixels, got {img.dtype}")
        if stack is None:
            stack = np.empty((len(names), *img.shape), img.dtype)
        elif img.shape != stack.shape[1:] or img.dtype != stack.dtype:
            raise ValueError(
                f"{fpath}: {img.shape} {img.dtype} differs from the first frame's "
                f"{stack.shape[1:]} {stack.dtype}"
            )
        if img.ctypes.data != stack[i].ctypes.data:  # not decoded in place
            stack[i] = img
    known = {"format", "pattern", "exposure_ms", "led", "frames", "bit_depth", "channel"}
    if stack is None:  # the schedule has frames, so names does too
        raise ValueError(f"{meta_path}: lists no frames")
    try:
        return CaptureSet(
            frames=stack,
            schedule=schedule,
            exposure_ms=float(meta.get("exposure_ms", DEFAULT_EXPOSURE_MS)),
            led=str(led),
            extra={k: v for k, v in meta.items() if k not in known},
            bit_depth=bit_depth,
            channel=channel,
        )
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{meta_path}: {exc}") from None
