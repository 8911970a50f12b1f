"""Uploaded capture sets: multipart (capture.json + frame PNGs) or one .zip, size-limited."""

from __future__ import annotations

import io
import tempfile
import zipfile
from pathlib import Path, PurePosixPath

from fastapi import HTTPException, Request
from starlette.datastructures import UploadFile

from app.capture.captureset import CaptureSet, read_capture_set

MAX_FILES = 200


async def read_body(request: Request, limit_bytes: int) -> bytes:
    """The whole request body, refusing (413) more than ``limit_bytes``."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit_bytes:
        raise HTTPException(413, f"upload: {int(declared)} bytes exceeds the limit of {limit_bytes} bytes")
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
    if not base or base in (".", ".."):
        raise ValueError(f"upload: invalid file name {name!r}")
    return base


def _extract_zip(data: bytes, dest: Path, limit_bytes: int) -> Path:
    """Unpack a zip (plain files only) and return the folder holding capture.json."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except zipfile.BadZipFile:
        raise ValueError("upload: not a valid zip file") from None
    with zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        if len(infos) > MAX_FILES:
            raise ValueError(f"upload: zip holds {len(infos)} files, at most {MAX_FILES} allowed")
        if sum(i.file_size for i in infos) > limit_bytes:
            raise HTTPException(413, f"upload: unpacked zip exceeds the limit of {limit_bytes} bytes")
        metas = [i for i in infos if PurePosixPath(i.filename).name == "capture.json"]
        if len(metas) != 1:
            raise ValueError(f"upload: the zip must hold exactly one capture.json, found {len(metas)}")
        folder = str(PurePosixPath(metas[0].filename).parent)
        for info in infos:
            p = PurePosixPath(info.filename)
            if str(p.parent) == folder:  # only the set's own folder; names are plain
                (dest / _safe_name(p.name)).write_bytes(zf.read(info))
    return dest


async def capture_from_request(request: Request, limit_bytes: int) -> CaptureSet:
    """Parse the upload into a :class:`CaptureSet`; ValueError (→ 422) names what is wrong."""
    body = await read_body(request, limit_bytes)
    ctype = request.headers.get("content-type", "")
    with tempfile.TemporaryDirectory(prefix="fringescope-upload-") as tmp:
        dest = Path(tmp)
        if ctype.startswith("multipart/form-data"):
            form = await request.form(max_files=MAX_FILES, max_fields=MAX_FILES, max_part_size=limit_bytes)
            files = [v for _, v in form.multi_items() if isinstance(v, UploadFile)]
            if not files:
                raise ValueError("upload: no files in the form (send capture.json + frames, or a .zip)")
            if len(files) == 1 and (files[0].filename or "").lower().endswith(".zip"):
                _extract_zip(await files[0].read(), dest, limit_bytes)
            else:
                for f in files:
                    (dest / _safe_name(f.filename or "")).write_bytes(await f.read())
        elif ctype.startswith(("application/zip", "application/x-zip-compressed", "application/octet-stream")):
            _extract_zip(body, dest, limit_bytes)
        else:
            raise HTTPException(415, "upload: send multipart/form-data or application/zip")
        if not (dest / "capture.json").is_file():
            raise ValueError("upload: capture.json is missing")
        try:
            return read_capture_set(dest)
        except ValueError as exc:
            # Messages name the temporary folder; keep only the file name for the user.
            raise ValueError(str(exc).replace(str(dest) + "/", "")) from None
