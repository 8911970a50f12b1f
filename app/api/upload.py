"""Uploaded capture sets: multipart (capture.json + frame PNGs) or one .zip, size-limited.

Bounded before anything is decoded: the body by the upload limit, zip members by their
declared sizes and ratio, file names by length, ``capture.json`` by size, depth and finite
numbers, and the frames by their PNG/TIFF headers (size against the calibration's, pixels
and decoded bytes against :class:`~app.capture.imageheader.FrameLimits`).
"""

from __future__ import annotations

import io
import json
import struct
import tempfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath

from fastapi import HTTPException, Request
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile

from app.capture.captureset import MAX_META_BYTES, CaptureSet, read_capture_set
from app.capture.imageheader import FrameLimits
from app.core.errors import InvalidRequest
from app.core.jsonlimits import loads_finite

MAX_FILES = 200
SUPPORTED_COMPRESSION = frozenset({zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED})
MAX_RATIO = 100  # a larger expansion of a member is refused as a zip bomb ...
RATIO_FLOOR_BYTES = 1 << 16  # ... once it unpacks to more than this (PNG frames barely compress)
MAX_NAME_CHARS = 128  # a file name longer than this is refused (the disk allows 255 bytes)


async def read_body(request: Request, limit_bytes: int) -> bytes:
    """The whole request body, refusing (413) more than ``limit_bytes``."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit_bytes:
        raise HTTPException(413, f"upload: {int(declared)} bytes exceeds the limit "
                                 f"of {limit_bytes} bytes")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit_bytes:
            raise HTTPException(413, f"upload: exceeds the limit of {limit_bytes} bytes")
        chunks.append(chunk)
    body = b"".join(chunks)
    request._body = body  # lets request.form() parse what was already read
    return body


def _safe_name(name: str) -> str:
    base = PurePosixPath(name.replace("\\", "/")).name
    if len(base) > MAX_NAME_CHARS or len(base.encode("utf-8", "surrogatepass")) > 255:
        raise InvalidRequest(f"upload: file name {base[:40]!r}… is {len(base)} characters long, "
                             f"at most {MAX_NAME_CHARS} allowed")
    if not base or base in (".", "..") or "\0" in base:
        raise InvalidRequest(f"upload: invalid file name {name[:40]!r}")
    return base


def _member_path(name: str) -> PurePosixPath:
    """A zip member's path, refusing absolute paths and ``..`` (path traversal)."""
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts or (p.parts and ":" in p.parts[0]):
        raise InvalidRequest(f"upload: zip member {name!r} points outside the archive")
    return p


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, budget: int) -> bytes:
    """A member's bytes, never more than it declares nor than ``budget`` (zip
    bombs, lying headers)."""
    if info.flag_bits & 0x1:
        raise InvalidRequest(f"upload: zip member {info.filename!r} is encrypted")
    if info.compress_type not in SUPPORTED_COMPRESSION:
        raise InvalidRequest(f"upload: zip member {info.filename!r} uses compression method "
                             f"{info.compress_type}; use stored or deflated")
    expands = info.file_size > MAX_RATIO * max(info.compress_size, 1)
    if expands and info.file_size > RATIO_FLOOR_BYTES:
        raise InvalidRequest(f"upload: zip member {info.filename!r} expands {info.file_size} "
                             f"bytes from {info.compress_size} (more than {MAX_RATIO}x): "
                             "refused as a zip bomb")
    if info.file_size > budget:
        raise HTTPException(413, f"upload: unpacked zip exceeds the limit of {budget} bytes")
    with zf.open(info) as f:
        data = f.read(info.file_size + 1)
    if len(data) != info.file_size:
        raise InvalidRequest(f"upload: zip member {info.filename!r} does not "
                             "hold its declared size")
    return data


def _extract_zip(data: bytes, dest: Path, limit_bytes: int) -> Path:
    """Unpack a zip (plain files only) and return the folder holding capture.json.

    Every malformed archive is an ``InvalidRequest`` naming the fault (not a zip, truncated,
    bad CRC, encrypted, unknown compression, path traversal, zip bomb); too much data is 413.
    """
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, struct.error):
        raise InvalidRequest("upload: not a valid zip file") from None
    with zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        if len(infos) > MAX_FILES:
            raise InvalidRequest(f"upload: zip holds {len(infos)} files, at "
                                 f"most {MAX_FILES} allowed")
        paths = [_member_path(i.filename) for i in infos]
        if sum(i.file_size for i in infos) > limit_bytes:
            raise HTTPException(413,
                                f"upload: unpacked zip exceeds the limit of {limit_bytes} bytes")
        metas = [p for p in paths if p.name == "capture.json"]
        if len(metas) != 1:
            raise InvalidRequest("upload: the zip must hold exactly one "
                                 f"capture.json, found {len(metas)}")
        folder = metas[0].parent
        budget = limit_bytes
        for info, p in zip(infos, paths, strict=True):
            if p.parent != folder:  # only the set's own folder; names are plain
                continue
            try:
                content = _read_member(zf, info, budget)
            except (zipfile.BadZipFile, EOFError, zlib.error, struct.error, OSError, ValueError,
                    NotImplementedError, RuntimeError) as exc:
                raise InvalidRequest(f"upload: zip member {info.filename!r} is corrupt "
                                     f"({exc})") from None
            budget -= len(content)
            (dest / _safe_name(p.name)).write_bytes(content)
    return dest


def _read_set(dest: Path, limits: FrameLimits) -> CaptureSet:
    """The unpacked set, ``capture.json`` checked for non-finite numbers, frames bounded."""
    meta = dest / "capture.json"
    if not meta.is_file():
        raise InvalidRequest("upload: capture.json is missing")
    try:
        with open(meta, "rb") as fh:
            loads_finite(fh.read(MAX_META_BYTES + 1)[:MAX_META_BYTES], "capture.json")
    except ValueError as exc:
        if not isinstance(exc, json.JSONDecodeError):  # not JSON: read_capture_set says so
            raise InvalidRequest(str(exc)) from None
    try:
        return read_capture_set(dest, limits=limits)
    except (ValueError, KeyError, TypeError) as exc:  # the uploaded files are the user's input
        # Messages name the temporary folder; keep only the file name for the user.
        raise InvalidRequest(str(exc).replace(str(dest) + "/", "")) from None


async def capture_from_request(request: Request, limit_bytes: int, *,
                               frame_size: tuple[int, int] | None = None) -> CaptureSet:
    """Parse the upload into a :class:`CaptureSet`; ``InvalidRequest`` (422) names what is wrong.

    ``frame_size`` (width, height): the size every frame must have (the calibration's),
    checked on the image headers before any frame is decoded.
    """
    limits = FrameLimits(frame_size=frame_size)
    body = await read_body(request, limit_bytes)
    ctype = request.headers.get("content-type", "")
    with tempfile.TemporaryDirectory(prefix="fringescope-upload-") as tmp:
        dest = Path(tmp)
        if ctype.startswith("multipart/form-data"):
            form = await request.form(max_files=MAX_FILES, max_fields=MAX_FILES,
                                      max_part_size=limit_bytes)
            files = [v for _, v in form.multi_items() if isinstance(v, UploadFile)]
            if not files:
                raise InvalidRequest("upload: no files in the form (send capture.json "
                                     "+ frames, or a .zip)")
            if len(files) == 1 and (files[0].filename or "").lower().endswith(".zip"):
                await run_in_threadpool(_extract_zip, await files[0].read(), dest, limit_bytes)
            else:
                for f in files:
                    (dest / _safe_name(f.filename or "")).write_bytes(await f.read())
        elif ctype.startswith(("application/zip", "application/x-zip-compressed",
                               "application/octet-stream")):
            await run_in_threadpool(_extract_zip, body, dest, limit_bytes)
        else:
            raise HTTPException(415, "upload: send multipart/form-data or application/zip")
        return await run_in_threadpool(_read_set, dest, limits)
