"""Recordings: live sessions on disk, one capture-set folder per depth map.

Layout under ``<data_dir>/recordings/<name>/``::

    session.json          {"format": "fringescope.recording/1", "name", "started",
                           "stopped", "settings", "sets": [{"folder", "timestamp", ...}]}
    set_0000/             a capture set (capture.json + frame_XX.png or frame_XX.npy.zst)
    set_0001/ …           + depth.npy

A recording the service did not close (it was killed, or the power went) keeps
``"stopped": null``; :func:`recover_interrupted`, run when the service starts, marks it
``"interrupted": true`` with ``stopped`` at its last whole set.

Data that is never lost: every set folder is built under a hidden temporary name
and renamed into place whole (:func:`app.atomic.atomic_directory`), and only then
listed in ``session.json``, which is itself replaced atomically. A crash mid-write
leaves the earlier sets and the previous ``session.json`` intact; the half-written
set stays a hidden ``.set_XXXX.*.partial`` folder that no reader lists (and that
:func:`remove_stale_partials` deletes). Names are validated so nothing escapes the
data folder, and reads never follow a symbolic link: a link planted in a recording (to
``/etc/passwd``, to ``/etc``, to another recording) is neither listed, nor zipped, nor read.
"""

from __future__ import annotations

import errno
import io
import json
import os
import re
import shutil
import stat
import threading
import time
import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.atomic import atomic_write_text
from app.capture.captureset import ZSTD_SUFFIX, CaptureSet, frame_names, write_capture_set
from app.core.encoding import npy_bytes

FORMAT = "fringescope.recording/1"
SESSION_FILE = "session.json"
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_SET_PATTERN = re.compile(r"^set_\d{4,}$")
_FILE_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
MAX_SESSION_BYTES = 64 * 1024 * 1024  # session.json grows by ~1 kB a set


def validate_name(name: Any, what: str = "name") -> str:
    """Return ``name`` if it is a safe single path component, else raise ``ValueError``.

    Allowed: 1–64 characters from ``A–Z a–z 0–9 . _ -``, starting with a letter or
    digit — so no separators, no ``..``, no hidden files, nothing outside the folder.
    ``what`` names the argument in the message (e.g. ``"recording name"``).
    """
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise ValueError(
            f"{what}: {name!r} is not allowed (1-64 characters A-Z a-z 0-9 . _ -, "
            "starting with a letter or digit)"
        )
    return name


def safe_child(root: str | os.PathLike[str], name: str, what: str = "name") -> Path:
    """``root / name`` after :func:`validate_name`, never a symbolic link, inside ``root``."""
    base = Path(root).resolve()
    path = base / validate_name(name, what)
    if path.is_symlink():  # planted in the data folder: it must not lead out, nor elsewhere in
        raise ValueError(f"{what}: {name!r} is a symbolic link (it may lead outside {base})")
    if path.resolve().parent != base:
        raise ValueError(f"{what}: {name!r} resolves outside {base}")
    return path


def _real_dir(path: Path) -> bool:
    """A folder itself, not a symbolic link to one."""
    return path.is_dir() and not path.is_symlink()


def _real_file(path: Path) -> bool:
    """A regular file itself, not a symbolic link to one."""
    return path.is_file() and not path.is_symlink()


def open_regular(path: str | os.PathLike[str]) -> io.BufferedReader:
    """Open a regular file for reading without following a symbolic link.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is a symbolic link or not a regular file.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ValueError(f"{Path(path).name}: a symbolic link, not read") from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO or device would block or never end
        os.close(fd)
        raise ValueError(f"{Path(path).name}: not a regular file")
    return os.fdopen(fd, "rb")


def check_no_links(folder: Path) -> None:
    """``ValueError`` if ``folder`` is, or directly holds, a symbolic link."""
    if folder.is_symlink():
        raise ValueError(f"{folder.name}: a symbolic link, not read")
    for entry in os.scandir(folder):
        if entry.is_symlink():
            raise ValueError(f"{folder.name}/{entry.name}: a symbolic link, not read")


def read_set_file(root: str | os.PathLike[str], name: str, folder: str, file: str) -> bytes:
    """The bytes of ``file`` in set ``folder`` of recording ``name``, no link followed.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a bad name, or a symbolic link on the way.
    """
    if not _SET_PATTERN.fullmatch(folder) or not _FILE_PATTERN.fullmatch(file):
        raise ValueError(f"set file: {folder!r}/{file!r} is not allowed")
    set_dir = safe_child(root, name, "recording name") / folder
    if set_dir.is_symlink():
        raise ValueError(f"{folder}: a symbolic link, not read")
    with open_regular(set_dir / file) as fh:
        return fh.read()


def recordings_root(data_dir: str | os.PathLike[str]) -> Path:
    """The folder that holds all recordings, ``<data_dir>/recordings``."""
    return Path(data_dir) / "recordings"


def default_name(now: float | None = None) -> str:
    """A fresh recording name from the UTC clock, e.g. ``rec_20260121-142501``."""
    stamp = datetime.fromtimestamp(time.time() if now is None else now, UTC)
    return stamp.strftime("rec_%Y%m%d-%H%M%S")


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds")


def depth_npy_bytes(depth_mm: npt.ArrayLike) -> bytes:
    """A depth map as ``.npy`` bytes: (H, W) float32 mm, NaN where invalid."""
    return npy_bytes(_depth_array(depth_mm))


def depth_tiff_bytes(depth_mm: npt.ArrayLike) -> bytes:
    """A depth map as a 32-bit float TIFF (one page, (H, W), mm, NaN where invalid)."""
    import tifffile

    arr = _depth_array(depth_mm)
    buf = io.BytesIO()
    tifffile.imwrite(buf, arr, photometric="minisblack", metadata={"unit": "mm"})
    return buf.getvalue()


def _depth_array(depth_mm: npt.ArrayLike) -> npt.NDArray[np.float32]:
    arr = np.asarray(depth_mm)
    if arr.ndim != 2:
        raise ValueError(f"depth_mm: expected shape (H, W), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"depth_mm: expected a float array, got {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float32)


class Recording:
    """An open recording session that capture sets are appended to.

    Args:
        root: the recordings folder (``recordings_root(data_dir)``).
        name: the session name (see :func:`validate_name`); must not exist yet.
        settings: a JSON-able snapshot of the instrument settings, kept in
            ``session.json``.

    Thread-safe: :meth:`add_set` and :meth:`close` may be called from any thread.
    """

    def __init__(
        self, root: str | os.PathLike[str], name: str, *, settings: dict[str, Any] | None = None
    ) -> None:
        validate_name(name, "recording name")
        if name.lower().endswith(".zip"):
            raise ValueError(f"recording name: {name!r} must not end in .zip")
        Path(root).mkdir(parents=True, exist_ok=True)
        self.path = safe_child(root, name, "recording name")
        self.name = name
        self._lock = threading.Lock()
        self._closed = False
        try:
            self.path.mkdir()
        except FileExistsError:
            raise FileExistsError(f"recording {name!r} already exists") from None
        self._session: dict[str, Any] = {
            "format": FORMAT,
            "name": name,
            "started": _iso(time.time()),
            "stopped": None,
            "settings": settings or {},
            "sets": [],
        }
        self._write_session()

    @property
    def n_sets(self) -> int:
        with self._lock:
            return len(self._session["sets"])

    @property
    def closed(self) -> bool:
        return self._closed

    def add_set(
        self,
        capture: CaptureSet,
        *,
        depth_mm: npt.ArrayLike | None = None,
        timestamp: float | None = None,
        info: dict[str, Any] | None = None,
        codec: str = "png",
        encoded: list[bytes] | None = None,
        change_mm: npt.ArrayLike | None = None,
    ) -> str:
        """Append one capture set (and its depth map) and return its folder name.

        Args:
            capture: the raw fringe frames and their metadata.
            depth_mm: (H, W) float depth map in mm (NaN invalid), saved as ``depth.npy``.
            timestamp: acquisition time, seconds since the epoch (default: now).
            info: small JSON-able extras for this set's entry in ``session.json``.
            codec: how the frames are stored, ``png`` or ``zstd`` (see
                :mod:`app.capture.captureset`).
            encoded: the frames already encoded with ``codec``
                (:func:`app.capture.captureset.encode_frames`), so that encoding can run
                beside the previous set's writing.
            change_mm: (H, W) change map Δ against the reference in mm (NaN not compared),
                saved as ``change.npy`` (float32).
        """
        with self._lock:
            if self._closed:
                raise ValueError(f"recording {self.name!r} is closed")
            index = len(self._session["sets"])
            folder = f"set_{index:04d}"
            t = time.time() if timestamp is None else float(timestamp)
            extra = {"depth.npy": depth_npy_bytes(depth_mm)} if depth_mm is not None else {}
            if change_mm is not None:
                extra["change.npy"] = depth_npy_bytes(change_mm)
            stamped = CaptureSet(
                frames=capture.frames, schedule=capture.schedule, exposure_ms=capture.exposure_ms,
                led=capture.led, extra={**capture.extra, "timestamp": _iso(t), "index": index},
                bit_depth=capture.bit_depth,
            )
            write_capture_set(self.path / folder, stamped, extra_files=extra, codec=codec,
                              encoded=encoded)
            entry = {"folder": folder, "timestamp": _iso(t), "files": sorted(
                ["capture.json", *frame_names(capture.frames.shape[0], codec), *extra]
            ), **(info or {})}
            self._session["sets"].append(entry)
            try:
                self._write_session()
            except BaseException:
                # session.json still lists the old sets; keep memory in step with disk
                self._session["sets"].pop()
                shutil.rmtree(self.path / folder, ignore_errors=True)
                raise
            return folder

    def close(self) -> dict[str, Any]:
        """Mark the session stopped (idempotent) and return its ``session.json`` content."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._session["stopped"] = _iso(time.time())
                self._write_session()
            copy: dict[str, Any] = json.loads(json.dumps(self._session))
            return copy

    def _write_session(self) -> None:
        atomic_write_text(self.path / SESSION_FILE, json.dumps(self._session, indent=2) + "\n")


def read_session(root: str | os.PathLike[str], name: str) -> dict[str, Any]:
    """The ``session.json`` of recording ``name``; ``FileNotFoundError`` if there is none.

    Only sets whose folder exists are listed (a set removed by hand is dropped, a
    half-written one was never listed).
    """
    path = safe_child(root, name, "recording name")
    try:
        with open_regular(path / SESSION_FILE) as fh:
            session = json.loads(fh.read(MAX_SESSION_BYTES).decode("utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"recording {name!r} not found") from None
    except (OSError, ValueError, RecursionError) as exc:  # incl. a link, bad UTF-8, not JSON
        raise ValueError(f"recording {name!r}: unreadable {SESSION_FILE} ({exc})") from None
    if not isinstance(session, dict) or session.get("format") != FORMAT:
        raise ValueError(f"recording {name!r}: {SESSION_FILE} is not {FORMAT}")
    sets = [
        s for s in session.get("sets", [])
        if isinstance(s, dict) and _SET_PATTERN.fullmatch(str(s.get("folder", "")))
        and _real_dir(path / s["folder"])
    ]
    session["sets"] = sets
    session["n_sets"] = len(sets)
    session["bytes"] = sum(f.stat().st_size for f in _session_files(path, sets))
    return session


def list_recordings(root: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Summaries (name, started, stopped, n_sets, bytes) of every readable recording, by name."""
    base = Path(root)
    if not base.is_dir():
        return []
    out = []
    for child in sorted(base.iterdir()):
        if not (_real_dir(child) and NAME_PATTERN.fullmatch(child.name)):
            continue
        try:
            s = read_session(base, child.name)
        except (FileNotFoundError, ValueError):
            continue  # a folder without a whole session.json is not a recording
        summary = {k: s.get(k) for k in ("name", "started", "stopped", "n_sets", "bytes")}
        out.append({**summary, "interrupted": bool(s.get("interrupted", False))})
    return out


def recover_interrupted(root: str | os.PathLike[str], *, active: str | None = None) -> list[str]:
    """Close every recording left open by a service that stopped without closing it.

    Each one keeps its whole sets (those listed in ``session.json`` whose folder exists)
    and is marked ``"interrupted": true`` with ``stopped`` set to its last set's time stamp
    (its start when it has none). ``active`` names a recording being written now, left
    alone. Returns the names marked, by name.
    """
    base = Path(root)
    if not base.is_dir():
        return []
    marked = []
    for child in sorted(base.iterdir()):
        if not (child.is_dir() and NAME_PATTERN.fullmatch(child.name)) or child.name == active:
            continue
        try:
            session = read_session(base, child.name)
        except (FileNotFoundError, ValueError):
            continue
        if session.get("stopped") is not None:
            continue
        sets = session["sets"]
        session["stopped"] = sets[-1]["timestamp"] if sets else session.get("started")
        session["interrupted"] = True
        for derived in ("n_sets", "bytes"):  # computed by read_session, not stored
            session.pop(derived, None)
        atomic_write_text(child / SESSION_FILE, json.dumps(session, indent=2) + "\n")
        marked.append(child.name)
    return marked


def delete_recording(root: str | os.PathLike[str], name: str) -> None:
    """Remove recording ``name``; ``FileNotFoundError`` if it does not exist."""
    path = safe_child(root, name, "recording name")
    if not _real_file(path / SESSION_FILE):
        raise FileNotFoundError(f"recording {name!r} not found")
    # rename first so a crash mid-delete never leaves a half recording that still lists
    trash = path.with_name(f".{path.name}.deleted")
    shutil.rmtree(trash, ignore_errors=True)
    os.replace(path, trash)
    shutil.rmtree(trash, ignore_errors=True)


def remove_stale_partials(root: str | os.PathLike[str]) -> int:
    """Delete hidden leftovers of interrupted writes under ``root``; return how many."""
    base = Path(root)
    if not base.is_dir():
        return 0
    stale = [p for p in base.glob(".*.deleted") if p.is_dir()]
    for rec in base.iterdir():
        if rec.is_dir() and not rec.name.startswith("."):
            stale += [p for p in rec.glob(".*.partial") if p.is_dir()]
            stale += [p for p in rec.glob(".*.tmp") if p.is_file()]
    for p in stale:
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    return len(stale)


def _session_files(path: Path, sets: list[dict[str, Any]]) -> Iterator[Path]:
    yield path / SESSION_FILE
    for s in sets:
        folder = path / s["folder"]
        if not _real_dir(folder):
            continue
        for f in sorted(folder.iterdir()):
            if _real_file(f) and _FILE_PATTERN.fullmatch(f.name):
                yield f


class _Sink(io.RawIOBase):
    """An unseekable write-only stream whose bytes are collected for a generator."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.pos = 0
        self.buffered = 0

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        data = bytes(b)
        self.chunks.append(data)
        self.pos += len(data)
        self.buffered += len(data)
        return len(data)

    def tell(self) -> int:  # zipfile asks; an unseekable stream may still report position
        return self.pos

    def take(self) -> bytes:
        data = b"".join(self.chunks)
        self.chunks.clear()
        self.buffered = 0
        return data


def iter_zip(root: str | os.PathLike[str], name: str,
             chunk_bytes: int = 1 << 20) -> Iterator[bytes]:
    """Stream recording ``name`` as a zip archive, a chunk at a time (constant memory).

    The archive holds ``<name>/session.json`` and the listed set folders. PNG frames
    and zstd frames are stored (already compressed), everything else deflated.
    ``FileNotFoundError`` (raised before the first chunk) if the recording does not exist.
    """
    session = read_session(root, name)  # raises before streaming starts
    path = safe_child(root, name, "recording name")
    files = list(_session_files(path, session["sets"]))

    def generate() -> Iterator[bytes]:
        sink = _Sink()
        with zipfile.ZipFile(sink, "w", allowZip64=True) as zf:
            for f in files:
                try:  # closed below, interleaved with yields; a link swapped in is not followed
                    fh = open_regular(f)
                except (FileNotFoundError, ValueError):
                    continue  # deleted (or replaced by a link) while streaming: skip it
                with fh:
                    st = os.fstat(fh.fileno())
                    info = zipfile.ZipInfo(f"{name}/{f.relative_to(path).as_posix()}",
                                           time.gmtime(max(st.st_mtime, 315532800))[:6])
                    info.file_size = size = st.st_size
                    stored = f.suffix == ".png" or f.name.endswith(ZSTD_SUFFIX)
                    info.compress_type = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
                    with zf.open(info, "w", force_zip64=size > 0x7FFF0000) as out:
                        while block := fh.read(chunk_bytes):
                            out.write(block)
                            if sink.buffered >= chunk_bytes:
                                yield sink.take()
                if sink.buffered:
                    yield sink.take()
        if sink.buffered:
            yield sink.take()

    return generate()
