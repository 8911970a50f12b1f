"""``fringescope reprocess``: whole recordings through the per-set job on Dask distributed.

The client plans one set task per capture set (or per exposure bracket of consecutive sets),
skips sets whose outputs already carry the same digest (calibration + options + files + the
software that made them), ships the calibration once to every worker
(``scatter(broadcast=True)``) and submits the set tasks, a few consecutive ones per Dask
task (:func:`sets_per_task`: Dask's own cost per task is a few ms of CPU); each worker reads
its sets itself (frames never travel through the client), runs
:func:`app.batch.setjob.reconstruct_captures`, writes the files atomically, and returns a
small row per set. A set that fails is a row with its error. A worker that dies mid-task is
replaced by the scheduler, which reruns the task elsewhere (outputs are rewritten whole).

Paths are fsspec URLs (a plain path is the local file system): workers on other machines
read recordings from shared storage or an object store.

Output layout::

    OUT/<recording>/<set folder>/depth.npy, sigma.npy, reason.png [, points.ply, depth.png]
    OUT/<recording>/<set folder>/reprocess.json   written last: digest, inputs, the row
    OUT/<recording>/sets.parquet                  one row per set
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import logging
import math
import os
import pathlib
import sys
import tempfile
import time
import uuid
import warnings
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, BinaryIO, TextIO

from app.atomic import fsync_dir
from app.batch.setjob import (
    ALL_FILES,
    FileWriter,
    ReconOptions,
    check_bracket,
    new_reconstructor,
)
from app.core.calibration import Calibration

if TYPE_CHECKING:
    import fsspec
    from distributed import Client, LocalCluster

    from app.capture import CaptureSet
    from app.recon import Reconstructor

log = logging.getLogger("fringescope.batch")

FORMAT = "fringescope.reprocess/1"
META_FILE = "reprocess.json"
TABLE_FILE = "sets.parquet"
SESSION_FILE = "session.json"
CAPTURE_FILE = "capture.json"
DEFAULT_FILES = ("depth.npy", "sigma.npy", "reason.png")
#: Dask settings of the embedded cluster's workers. No statistical profiler sampling every
#: thread's stack 100 times a second (it feeds the dashboard, which is off), and the
#: event-loop watchdog and system monitor at a slower pace: on an idle worker these cost ~2 %
#: of a core. One malloc arena (set before the worker process starts): a task runs in a
#: worker thread, whose own arena handed a set's large arrays back to the system after each
#: set, to be faulted in afresh by the next (~1,350 page faults per set of 1384 x 1032).
#: Workers started by hand take them as environment variables (README).
WORKER_CONFIG: dict[str, object] = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": "1",
}
#: at most this many sets per Dask task, and at least this many tasks per worker
MAX_SETS_PER_TASK, TASKS_PER_WORKER = 8, 4
#: the table's columns, in order (floats are NaN where a failed set has no value)
COLUMNS = ("index", "folder", "timestamp", "exposure_ms", "valid_fraction", "median_sigma_mm",
           "motion_share", "recon_ms", "decode_ms", "task_ms", "cpu_ms", "decode_cpu_ms",
           "recon_cpu_ms", "write_cpu_ms", "status", "error")


@dataclass(frozen=True)
class SetTask:
    """One unit of work: a set (or a bracket of consecutive sets) of one recording.

    Attributes:
        recording: the recording's name (its output sub-folder).
        index: position of the (first) set in the recording.
        folders: the set folder names (several: an exposure bracket, fused).
        urls: the set folders' URLs.
        out_url: the output folder's URL for this set.
        files: the output files to write (a subset of :data:`~app.batch.setjob.ALL_FILES`).
        digest: hash of the calibration, options and files; kept in ``reprocess.json``.
        cal_key: hash of the calibration alone (the worker's reconstructor cache key).
    """

    recording: str
    index: int
    folders: tuple[str, ...]
    urls: tuple[str, ...]
    out_url: str
    files: tuple[str, ...]
    digest: str
    cal_key: str


@dataclass
class RecordingPlan:
    """A recording's tasks: ``todo`` to run, ``reused`` rows of sets already done."""

    name: str
    url: str
    out_url: str
    todo: list[SetTask] = field(default_factory=list)
    reused: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class Summary:
    """What a run did (the summary line and the exit code come from it)."""

    recordings: int
    sets: int
    done: int
    reused: int
    failed: int
    elapsed_s: float

    def line(self, out_url: str) -> str:
        rate = self.done / self.elapsed_s if self.elapsed_s > 0 else 0.0
        return (f"reprocess: {self.recordings} recording(s), {self.sets} set(s): {self.done} done, "
                f"{self.reused} reused, {self.failed} failed in {self.elapsed_s:.1f} s "
                f"({rate:.2f} sets/s) -> {out_url}")


# --- paths -----------------------------------------------------------------------------

def _fs(url: str) -> tuple[fsspec.AbstractFileSystem, str]:
    from fsspec.core import url_to_fs

    return url_to_fs(url)  # type: ignore[no-any-return]


def _join(url: str, *names: str) -> str:
    return "/".join([url.rstrip("/"), *names])


def _is_local(fs: fsspec.AbstractFileSystem) -> bool:
    from fsspec.implementations.local import LocalFileSystem

    return isinstance(fs, LocalFileSystem)


def write_bytes(url: str, data: bytes) -> None:
    """Write ``data`` to ``url`` whole: a local file via a renamed temporary (never half
    written), an object store in one put."""
    fs, path = _fs(url)
    if _is_local(fs):
        from app.atomic import atomic_write_bytes

        atomic_write_bytes(path, data)
    else:
        fs.pipe_file(path, data)


def write_files(url: str, writers: Sequence[tuple[str, FileWriter]], *,
                durable: bool = True) -> None:
    """Write each ``(name, writer)`` file into the folder ``url``, each whole.

    Locally each file goes to a hidden temporary (``.NAME.*.tmp``) renamed over ``name``:
    a crash of the process leaves the old file or the new one. With ``durable`` all the
    temporaries are written, then synced, then renamed, and the folder is synced once
    after them: after a power cut too each name holds a whole file, and once this returns
    the files are on disk (so a file written later, e.g. ``reprocess.json``, is never on
    disk before them). An object store gets one put each.
    """
    fs, path = _fs(url)
    if not _is_local(fs):
        for name, write in writers:
            buf = io.BytesIO()
            write(buf)
            fs.pipe_file(_join(path, name), buf.getvalue())
        return
    os.makedirs(path, exist_ok=True)
    pending: list[tuple[str, str]] = []  # (temporary, name) not yet renamed
    try:
        with contextlib.ExitStack() as stack:
            opened = []
            for name, write in writers:
                fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=path)
                pending.append((tmp, name))
                fh = stack.enter_context(os.fdopen(fd, "wb"))
                write(fh)
                fh.flush()
                opened.append(fh)
            if durable:
                for fh in opened:
                    os.fsync(fh.fileno())
        while pending:
            tmp, name = pending[0]
            os.replace(tmp, os.path.join(path, name))
            pending.pop(0)
    except BaseException:
        for tmp, _name in pending:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        raise
    if durable:
        fsync_dir(path)


def remove_stale_temporaries(url: str) -> int:
    """Delete the hidden temporaries (``.NAME.*.tmp``) a killed writer left in a local output
    folder; return how many. A remote folder has none (each object is put whole)."""
    fs, path = _fs(url)
    if not _is_local(fs) or not os.path.isdir(path):
        return 0
    stale = [e for e in os.scandir(path) if e.name.startswith(".") and e.name.endswith(".tmp")]
    for e in stale:
        with contextlib.suppress(OSError):
            os.unlink(e.path)
    return len(stale)


def remove_file(url: str) -> None:
    """Delete the file at ``url`` if there is one; a local one for good (its folder synced
    after it), so that nothing written afterwards reaches the disk before its removal."""
    fs, path = _fs(url)
    if not _is_local(fs):
        with contextlib.suppress(FileNotFoundError):
            fs.rm_file(path)
        return
    try:
        os.unlink(path)
    except FileNotFoundError:
        return
    fsync_dir(os.path.dirname(path))


def read_text(url: str) -> str | None:
    """The UTF-8 text at ``url``; None if there is no such file."""
    fs, path = _fs(url)
    try:
        with fs.open(path, "rb") as fh:
            return bytes(fh.read()).decode("utf-8")
    except (FileNotFoundError, IsADirectoryError):
        return None


def read_set(url: str) -> CaptureSet:
    """A capture set through the public reader; a remote set is copied to a temporary
    folder first (the reader reads local folders)."""
    from app.capture import read_capture_set

    fs, path = _fs(url)
    if _is_local(fs):
        return read_capture_set(path)
    with tempfile.TemporaryDirectory(prefix="fringescope-set-") as tmp:
        fs.get(path.rstrip("/") + "/", tmp + "/", recursive=True)
        return read_capture_set(tmp)


def list_sets(url: str) -> list[str]:
    """The capture-set folder names of a recording, in order.

    A recording as the recorder writes it lists its sets in ``session.json``; any other
    folder gives its sub-folders that hold a ``capture.json``, by name.

    Raises:
        ValueError: ``url`` is not a folder, or has no capture sets.
    """
    fs, path = _fs(url)
    if not fs.isdir(path):
        raise ValueError(f"{url}: recording folder not found")
    session_text = read_text(_join(url, SESSION_FILE))
    if session_text is not None:
        try:
            session = json.loads(session_text)
            folders = [str(s["folder"]) for s in session["sets"]]
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{url}: unreadable {SESSION_FILE} ({exc})") from None
        folders = [f for f in folders if fs.isfile(_join(path, f, CAPTURE_FILE))]
    else:
        folders = sorted(
            name for name in (str(e).rstrip("/").rsplit("/", 1)[-1]
                              for e in fs.ls(path, detail=False))
            if not name.startswith(".") and fs.isfile(_join(path, name, CAPTURE_FILE))
        )
    if not folders:
        raise ValueError(f"{url}: not a recording (no {SESSION_FILE} listing sets and no "
                         f"sub-folders with {CAPTURE_FILE})")
    return folders


def recording_name(url: str) -> str:
    """The last component of a recording URL (its output sub-folder)."""
    return url.rstrip("/").rsplit("/", 1)[-1] or "recording"


# --- digests ---------------------------------------------------------------------------

def calibration_key(calibration: Calibration) -> str:
    """sha256 of the calibration's canonical JSON (independent of the file's layout)."""
    text = json.dumps(calibration.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


#: the parts of the ``app`` package whose code shapes a set's outputs: the numerics, the
#: contracts, capture-set reading, the writers
OUTPUT_CODE = ("atomic.py", "batch", "capture", "core", "recon")


def source_digest(root: pathlib.Path, parts: Sequence[str]) -> str:
    """sha256 of the ``.py`` files under ``root``'s ``parts`` (files or folders), with their
    paths relative to ``root``, in a fixed order."""
    h = hashlib.sha256()
    for part in parts:
        top = root / part
        files = [top] if top.is_file() else sorted(top.rglob("*.py"))
        for f in files:
            h.update(f.relative_to(root).as_posix().encode("utf-8") + b"\0")
            h.update(f.read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def software_key() -> str:
    """The build that makes outputs: Fringescope's version, the source of :data:`OUTPUT_CODE`
    and the numeric libraries' versions. A resumed run redoes the sets an older build made
    (their numbers may differ) instead of keeping them."""
    import cv2
    import numba
    import numpy

    import app

    spec = {"fringescope": app.__version__, "numpy": numpy.__version__,
            "numba": numba.__version__, "opencv": cv2.__version__,
            "source": source_digest(pathlib.Path(app.__file__).parent, OUTPUT_CODE)}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode("utf-8")).hexdigest()


def output_digest(cal_key: str, options: ReconOptions, files: Sequence[str], bracket: int) -> str:
    """sha256 of everything that shapes a set's outputs besides its frames (the software
    included: :func:`software_key`)."""
    spec = {"format": FORMAT, "calibration": cal_key, "options": options.to_dict(),
            "files": sorted(files), "bracket": bracket, "software": software_key()}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode("utf-8")).hexdigest()


def _reusable_row(task: SetTask) -> dict[str, Any] | None:
    """The saved row of a set whose outputs exist for ``task.digest``, else None."""
    text = read_text(_join(task.out_url, META_FILE))
    if text is None:
        return None
    try:
        meta = json.loads(text)
    except ValueError:
        return None
    if not isinstance(meta, dict) or meta.get("digest") != task.digest:
        return None
    if meta.get("inputs") != list(task.folders) or not isinstance(meta.get("row"), dict):
        return None
    fs, path = _fs(task.out_url)
    if not all(fs.isfile(_join(path, f)) for f in task.files):
        return None
    return {**meta["row"], "status": "reused", "error": ""}


# --- the worker's side -----------------------------------------------------------------

#: per worker process: the reconstructor (per-pixel tables) of each calibration, schedule
#: and options seen, so a task pays only for its own set
_BASES: dict[tuple[str, str, str], Reconstructor] = {}
_MAX_BASES = 4


def _base_reconstructor(cal_key: str, calibration: Calibration,
                        options: ReconOptions) -> Reconstructor:
    key = (cal_key, json.dumps(calibration.pattern.to_dict(), sort_keys=True),
           json.dumps(options.to_dict(), sort_keys=True))
    base = _BASES.get(key)
    if base is None:
        if len(_BASES) >= _MAX_BASES:
            _BASES.clear()
        base = _BASES[key] = new_reconstructor(calibration, options)
    return base


#: glibc's ``mallopt`` parameters, and the mmap threshold a worker gets: arrays up to it come
#: from the heap and are reused by the next set (glibc's own rule when no threshold is set)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 * 2**20
_process_ready = False


def one_core_per_task() -> None:
    """Run this thread's numerics on one core, and let the process reuse freed memory.

    numba's kernel threads are a per-thread setting, so it is made in the task's thread
    (also on workers started without ``NUMBA_NUM_THREADS=1``); OpenCV's pool is shared. A
    worker's parallelism is its task threads. Dask's nanny starts workers with
    ``MALLOC_TRIM_THRESHOLD_=65536``, which turns off glibc's dynamic mmap threshold: every
    large array of every set is then mapped and faulted in afresh (+85 ms CPU per set on
    1384 x 1032 frames); the process gets glibc's usual thresholds back (Linux, glibc only).
    """
    global _process_ready
    import numba

    if numba.get_num_threads() != 1:
        numba.set_num_threads(1)
    if _process_ready:
        return
    import ctypes

    import cv2

    cv2.setNumThreads(1)
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        libc.mallopt(M_TRIM_THRESHOLD, 2 * MMAP_THRESHOLD_BYTES)
    _process_ready = True


def _empty_row(task: SetTask) -> dict[str, Any]:
    nan = math.nan
    return {"index": task.index, "folder": task.folders[0], "timestamp": None, "exposure_ms": nan,
            "valid_fraction": nan, "median_sigma_mm": nan, "motion_share": nan, "recon_ms": nan,
            "decode_ms": nan, "task_ms": nan, "cpu_ms": nan, "decode_cpu_ms": nan,
            "recon_cpu_ms": nan, "write_cpu_ms": nan, "status": "failed", "error": ""}


def run_set(task: SetTask, calibration: Calibration, options: ReconOptions) -> dict[str, Any]:
    """Reconstruct one task's set(s) and write its files; return its table row.

    Runs on a Dask worker. Any failure of the set (unreadable frames, a schedule the
    calibration does not fit, a full disk) becomes the row's ``error`` with status
    ``failed``; the set's earlier outputs, if any, stay as they were.
    """
    from app.batch.setjob import output_writers, reconstruct_captures, set_statistics
    from app.service.schedules import calibration_for_schedule

    one_core_per_task()
    t0, cpu0, thread0 = time.perf_counter(), time.process_time(), time.thread_time()
    row = _empty_row(task)
    try:
        captures = [read_set(u) for u in task.urls]
        t_read, thread_read, cpu_read = time.perf_counter(), time.thread_time(), time.process_time()
        try:
            cal = calibration_for_schedule(calibration, captures[0].schedule)
        except ValueError as exc:
            raise ValueError(f"{task.folders[0]}: {exc}") from None
        check_bracket(captures, task.folders)
        recon = reconstruct_captures(captures, cal, options,
                                     base=_base_reconstructor(task.cal_key, cal, options))
        cpu_recon = time.process_time()
        res = recon.result
        stamp = captures[0].extra.get("timestamp")
        exposure_ms = float(captures[0].exposure_ms)
        del captures  # the frames: what follows needs only the result (a worker's peak memory)
        stats = set_statistics(res)
        row.update(
            timestamp=stamp if isinstance(stamp, str) else None,
            exposure_ms=exposure_ms,
            valid_fraction=stats.valid_fraction,
            median_sigma_mm=stats.median_sigma_mm,
            motion_share=stats.motion_share,
            recon_ms=float(res.elapsed_ms),
            decode_ms=(t_read - t0) * 1e3,
            # the decoding's CPU is this thread's; the noise fit + Reconstructor.run's the
            # process's, as numba's workqueue runs the kernel on a thread of its own
            decode_cpu_ms=(thread_read - thread0) * 1e3,
            recon_cpu_ms=(cpu_recon - cpu_read) * 1e3,
        )
        remove_stale_temporaries(task.out_url)  # of an earlier run of this task killed mid-write
        # the old digest goes first: a run stopped among the writes must not look finished
        remove_file(_join(task.out_url, META_FILE))
        thread_write = time.thread_time()
        # synced: on disk before the digest below is written
        write_files(task.out_url, list(output_writers(recon, options, task.files).items()))
        row.update(status="done", task_ms=(time.perf_counter() - t0) * 1e3,
                   cpu_ms=(time.process_time() - cpu0) * 1e3,
                   # encoding, writing, syncing and renaming run on this thread
                   write_cpu_ms=(time.thread_time() - thread_write) * 1e3)
        meta = {"format": FORMAT, "digest": task.digest, "inputs": list(task.folders),
                "files": list(task.files), "options": options.to_dict(), "row": row}
        meta_bytes = (json.dumps(meta, indent=2) + "\n").encode()

        def write_meta(fh: BinaryIO) -> None:
            fh.write(meta_bytes)
        # not synced: a power cut may lose it (or leave it empty), and the set is done again
        write_files(task.out_url, [(META_FILE, write_meta)], durable=False)
    except Exception as exc:  # noqa: BLE001 - a set that fails is a row, never the end of the batch
        row.update(status="failed", error=f"{type(exc).__name__}: {exc}".splitlines()[0],
                   task_ms=(time.perf_counter() - t0) * 1e3)
    return row


# --- the client's side -----------------------------------------------------------------

def plan(recordings: Sequence[str], calibration: Calibration, out_url: str,
         options: ReconOptions, *, files: Sequence[str] = DEFAULT_FILES,
         bracket: int = 1) -> list[RecordingPlan]:
    """Check the input and plan the tasks; ``ValueError`` (one line) before any work.

    Each recording must list capture sets, and its first set must fit the calibration
    (schedule by the carry-over rule, image size). Sets whose outputs exist with the same
    digest are planned as reused.
    """
    from app.service.schedules import calibration_for_schedule

    if bracket < 1:
        raise ValueError(f"--bracket: must be >= 1, got {bracket}")
    unknown = [f for f in files if f not in ALL_FILES]
    if unknown:
        raise ValueError(f"files: unknown {unknown}")
    cal_key = calibration_key(calibration)
    digest = output_digest(cal_key, options, files, bracket)
    names = [recording_name(u) for u in recordings]
    dupes = {n for n in names if names.count(n) > 1}
    if dupes:
        raise ValueError(f"recordings: two recordings named {sorted(dupes)[0]!r} would share "
                         "an output folder")
    plans = []
    for url, name in zip(recordings, names, strict=True):
        folders = list_sets(url)
        first = read_set(_join(url, folders[0]))
        try:
            cal = calibration_for_schedule(calibration, first.schedule)
            cal.check_frames(first.frames.shape)
        except ValueError as exc:
            raise ValueError(f"{_join(url, folders[0])}: {exc}") from None
        p = RecordingPlan(name, url, _join(out_url, name))
        for start in range(0, len(folders), bracket):
            group = tuple(folders[start:start + bracket])
            task = SetTask(name, start, group, tuple(_join(url, f) for f in group),
                           _join(p.out_url, group[0]), tuple(files), digest, cal_key)
            if len(group) < bracket:
                row = _empty_row(task)
                row["error"] = f"a bracket of {bracket} needs {bracket} sets, {len(group)} left"
                p.reused.append(row)
                continue
            saved = _reusable_row(task)
            if saved is not None:
                p.reused.append(saved)
            else:
                p.todo.append(task)
        plans.append(p)
    return plans


class Progress:
    """``12/40 sets  3.1 sets/s  ETA 0:00:09`` on a stream: redrawn in place on a terminal,
    a line per 10 % otherwise; silent when ``stream`` is None."""

    def __init__(self, total: int, stream: TextIO | None) -> None:
        self.total, self.stream, self.done = total, stream, 0
        self.t0 = time.perf_counter()
        self._tty = bool(stream is not None and stream.isatty())
        self._last_draw = 0.0
        self._last_decile = -1

    def step(self) -> None:
        self.done += 1
        if self.stream is None:
            return
        now = time.perf_counter()
        decile = 10 * self.done // max(1, self.total)
        if self._tty and (now - self._last_draw < 0.2 and self.done < self.total):
            return
        if not self._tty and decile == self._last_decile and self.done < self.total:
            return
        self._last_draw, self._last_decile = now, decile
        rate = self.done / max(now - self.t0, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else 0.0
        text = (f"reprocess: {self.done}/{self.total} sets  {rate:.2f} sets/s  "
                f"ETA {time.strftime('%H:%M:%S', time.gmtime(eta))}")
        self.stream.write(("\r" + text) if self._tty else text + "\n")
        if self._tty and self.done >= self.total:
            self.stream.write("\n")
        self.stream.flush()


@contextlib.contextmanager
def connect(scheduler: str | None, workers: int | None, *,
            timeout_s: float = 10.0) -> Iterator[Client]:
    """A Dask client: to ``scheduler`` (``tcp://HOST:PORT``), or to an embedded local
    cluster of ``workers`` single-threaded worker processes (default: the cores).

    Raises:
        ValueError: the scheduler cannot be reached, or has no worker, within ``timeout_s``.
    """
    import dask.config
    from distributed import Client, LocalCluster

    cluster: LocalCluster | None = None
    if not log.isEnabledFor(logging.DEBUG):  # Dask's own INFO chatter is not the user's business
        logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise ValueError(
                f"--scheduler {scheduler}: cannot connect ({exc})".splitlines()[0]) from None
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except (OSError, TimeoutError):
            client.close()
            raise ValueError(f"--scheduler {scheduler}: no worker joined within "
                             f"{timeout_s:g} s") from None
    else:
        n = workers or os.cpu_count() or 1
        if n < 1:
            raise ValueError(f"--workers: must be >= 1, got {n}")
        # a worker process is one core: its numba kernel runs one thread (Dask's nanny
        # already sets OMP/MKL/OPENBLAS_NUM_THREADS=1), so N workers never oversubscribe
        # no dashboard; the scheduler's HTTP server (health, metrics) on a free loopback port,
        # not on 8787, which another cluster on the machine may hold
        with dask.config.set(WORKER_CONFIG):  # the nanny hands it to its worker
            cluster = LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                dashboard_address=None, silence_logs=logging.CRITICAL,
                scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
                env={"NUMBA_NUM_THREADS": "1",
                     "NUMBA_THREADING_LAYER": os.environ.get("NUMBA_THREADING_LAYER",
                                                             "workqueue")})
        client = Client(cluster, set_as_default=False)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def write_table(out_url: str, rows: Sequence[dict[str, Any]]) -> str:
    """Write ``rows`` (sorted by index) as ``OUT/<recording>/sets.parquet``, whole; return
    its URL."""
    import pandas as pd

    with warnings.catch_warnings():  # fastparquet probes a pandas option deprecated in pandas 3
        warnings.simplefilter("ignore")
        import fastparquet

    ordered = sorted(rows, key=lambda r: int(r["index"]))
    frame = pd.DataFrame({c: [r.get(c) for r in ordered] for c in COLUMNS})
    frame["index"] = frame["index"].astype("int64")
    for c in ("exposure_ms", "valid_fraction", "median_sigma_mm", "motion_share", "recon_ms",
              "decode_ms", "task_ms", "cpu_ms", "decode_cpu_ms", "recon_cpu_ms",
              "write_cpu_ms"):
        frame[c] = pd.to_numeric(frame[c], errors="coerce").astype("float64")
    # UTC, stored without a zone (the writer's zone-aware path is deprecated in pandas 3)
    stamps = pd.to_datetime(frame["timestamp"], utc=True, errors="coerce")
    frame["timestamp"] = stamps.dt.tz_convert(None)
    for c in ("folder", "status", "error"):
        frame[c] = frame[c].fillna("").astype(str)
    url = _join(out_url, TABLE_FILE)
    with tempfile.TemporaryDirectory(prefix="fringescope-table-") as tmp:
        local = os.path.join(tmp, TABLE_FILE)
        fastparquet.write(local, frame, write_index=False, compression="ZSTD")
        with open(local, "rb") as fh:
            write_bytes(url, fh.read())
    return url


def sets_per_task(n_tasks: int, n_workers: int) -> int:
    """How many set tasks one Dask task runs: enough to spread Dask's own cost per task
    (a few ms of scheduler, client and worker CPU) over several sets, while every worker
    still gets at least :data:`TASKS_PER_WORKER` tasks to balance the end of the run."""
    if n_tasks < 0 or n_workers < 1:
        raise ValueError(f"n_tasks, n_workers: need >= 0 and >= 1, got {n_tasks}, {n_workers}")
    return max(1, min(MAX_SETS_PER_TASK, n_tasks // (TASKS_PER_WORKER * n_workers)))


def run_batch(tasks: Sequence[SetTask], calibration: Calibration,
              options: ReconOptions) -> list[dict[str, Any]]:
    """:func:`run_set` for each of ``tasks`` in turn (one Dask task); their rows."""
    return [run_set(t, calibration, options) for t in tasks]


def run_tasks(
    client: Client, tasks: Sequence[SetTask], calibration: Calibration, options: ReconOptions, *,
    on_submitted: Callable[[Client], None] | None = None, batch: int | None = None,
) -> Generator[tuple[SetTask, dict[str, Any]], None, None]:
    """Run ``tasks`` on the cluster; yield (task, row) as each finishes.

    The calibration goes to every worker once; each task reads its own frames. ``batch``
    consecutive tasks run as one Dask task (None: :func:`sets_per_task` for the workers
    connected now); their rows come together. A Dask task whose every attempt died with
    its worker gives failed rows. Leaving the loop early (Ctrl-C) cancels the tasks not
    yet finished.
    """
    from distributed import as_completed

    if batch is None:
        batch = sets_per_task(len(tasks), max(1, len(client.scheduler_info()["workers"])))
    if batch < 1:
        raise ValueError(f"batch: must be >= 1, got {batch}")
    cal_future = client.scatter(calibration, broadcast=True, hash=False)
    run_id = uuid.uuid4().hex[:8]
    groups = [tuple(tasks[i:i + batch]) for i in range(0, len(tasks), batch)]
    futures = {
        client.submit(run_batch, g, cal_future, options, pure=False,
                      key=f"reprocess-{run_id}-{g[0].recording}-{g[0].folders[0]}-{len(g)}"): g
        for g in groups
    }
    if on_submitted is not None:
        on_submitted(client)
    finished = False
    try:
        for fut in as_completed(futures, loop=client.loop):
            group = futures[fut]
            try:
                rows = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. the task killed every worker it ran on
                rows = []
                for task in group:
                    row = _empty_row(task)
                    row["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0]
                    rows.append(row)
            fut.release()
            yield from zip(group, rows, strict=True)
        finished = True
    finally:
        if not finished:
            client.cancel(list(futures))
        cal_future.release()


def reprocess(
    recordings: Sequence[str], calibration: Calibration, out_url: str, options: ReconOptions, *,
    files: Sequence[str] = DEFAULT_FILES, bracket: int = 1, workers: int | None = None,
    scheduler: str | None = None, progress: TextIO | None = None, timeout_s: float = 10.0,
    on_submitted: Callable[[Client], None] | None = None,
) -> Summary:
    """Reprocess ``recordings`` into ``out_url`` (see the module docstring).

    Args:
        recordings: recording folder URLs (or plain paths).
        calibration: the calibration (shipped once to every worker).
        out_url: the output folder URL.
        options: the reconstruction's options (as ``fringescope reconstruct`` takes them).
        files: the output files per set.
        bracket: fuse each run of this many consecutive sets as an exposure bracket.
        workers: local worker processes (default the cores); ignored with ``scheduler``.
        scheduler: ``tcp://HOST:PORT`` of an existing Dask scheduler.
        progress: stream for the progress bar (None: quiet).
        timeout_s: how long to wait for the scheduler and its first worker, s.
        on_submitted: called with the client once every task is submitted.

    Returns:
        :class:`Summary`. Bad input raises ``ValueError`` before any task runs. On
        Ctrl-C the pending tasks are cancelled and the tables of the sets finished so far
        are written before ``KeyboardInterrupt`` propagates.
    """
    t0 = time.perf_counter()
    plans = plan(recordings, calibration, out_url, options, files=files, bracket=bracket)
    rows: dict[str, list[dict[str, Any]]] = {p.name: list(p.reused) for p in plans}
    todo = [t for p in plans for t in p.todo]
    done = failed = 0
    if todo:
        with connect(scheduler, workers, timeout_s=timeout_s) as client:
            bar = Progress(len(todo), progress)
            try:
                with contextlib.closing(run_tasks(client, todo, calibration, options,
                                                  on_submitted=on_submitted)) as results:
                    for task, row in results:
                        rows[task.recording].append(row)
                        done += row["status"] == "done"
                        failed += row["status"] == "failed"
                        bar.step()
            except KeyboardInterrupt:
                _write_tables(plans, rows)
                raise
    _write_tables(plans, rows)
    failed += sum(r["status"] == "failed" for p in plans for r in p.reused)
    reused = sum(r["status"] == "reused" for p in plans for r in p.reused)
    return Summary(len(plans), sum(len(r) for r in rows.values()), done, reused, failed,
                   time.perf_counter() - t0)


def _write_tables(plans: Sequence[RecordingPlan], rows: dict[str, list[dict[str, Any]]]) -> None:
    for p in plans:
        write_table(p.out_url, rows[p.name])


def stderr_or_none(quiet: bool) -> TextIO | None:
    """The progress stream: stderr unless ``quiet``."""
    return None if quiet else sys.stderr
