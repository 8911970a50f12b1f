"""The simulator's traced scene geometry, cached on disk between starts.

Tracing a named scene through the rig (ray casting, print texture, blur, projector
coordinates) costs seconds of CPU at every start, yet depends only on the scene's name, the
rig, the schedule, the sensor, the projector's response and the simulator's code. The arrays
are kept in ``<cache_dir>/sim-geometry-<key>.npz``, ``key`` a SHA-256 of those parameters
and of the simulator's source files (a code change makes a new key). Written atomically
(a temporary file renamed into place); a file that does not load is removed and the scene
traced again; at most ``MAX_FILES`` are kept (the least recently used go first).
"""

from __future__ import annotations

import functools
import hashlib
import io
import logging
import os
import threading
import zipfile
from pathlib import Path

import numpy as np
import numpy.typing as npt

from app.atomic import atomic_write_bytes

__all__ = ["MAX_FILES", "cache_key", "load", "save", "save_in_background"]

log = logging.getLogger("fringescope.sim")

MAX_FILES = 4
_PREFIX = "sim-geometry-"
Geometry = dict[str, npt.NDArray[np.generic]]


@functools.cache
def _source_digest() -> str:
    """SHA-256 of the simulator package's Python sources and numpy's version."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256(np.__version__.encode())
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def cache_key(parameters: tuple[object, ...]) -> str:
    """The cache key of a geometry made from ``parameters`` (their ``repr`` must identify
    them: names, frozen dataclasses, numbers) by the current simulator code."""
    return hashlib.sha256((_source_digest() + repr(parameters)).encode()).hexdigest()[:32]


def _path(cache_dir: Path, key: str) -> Path:
    return cache_dir / f"{_PREFIX}{key}.npz"


def load(cache_dir: Path, key: str) -> Geometry | None:
    """The arrays stored under ``key``, or None (absent, or unreadable: then removed)."""
    path = _path(cache_dir, key)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
        os.utime(path)  # recently used: kept when older ones are pruned
        return arrays
    except FileNotFoundError:
        return None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        log.warning("simulator geometry cache %s unreadable (%s): tracing the scene again",
                    path, exc)
        path.unlink(missing_ok=True)
        return None


def save_in_background(cache_dir: Path, key: str, arrays: Geometry) -> threading.Thread:
    """:func:`save` on a thread of its own: the first frames need not wait for the disk. Not a
    daemon: a server stopped right after its first depth still leaves the file whole."""
    thread = threading.Thread(target=save, args=(cache_dir, key, arrays), daemon=False,
                              name="fringescope-sim-geometry-cache")
    thread.start()
    return thread


def save(cache_dir: Path, key: str, arrays: Geometry) -> None:
    """Store ``arrays`` under ``key`` atomically; a failure is logged, never raised (a cache)."""
    try:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as npz:  # np.savez's layout
            for name, array in arrays.items():
                with npz.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)
        atomic_write_bytes(_path(cache_dir, key), buf.getvalue())
        files = sorted(cache_dir.glob(f"{_PREFIX}*.npz"), key=lambda p: p.stat().st_mtime)
        for old in files[:-MAX_FILES]:
            old.unlink(missing_ok=True)
    except OSError as exc:
        log.warning("simulator geometry cache not written to %s: %s", cache_dir, exc)
