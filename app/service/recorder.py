"""Recording the live instrument: every whole fringe set to disk, with its depth map.

A collector thread follows two public slots of the Instrument: ``acquisition.sets``
(each whole raw set, as grabbed) and ``results`` (each published depth map). A raw set
is paired with the depth map reconstructed from it (matched by the frames' timestamps);
a set the reconstruction skipped (newest-wins queue, no calibration, rolling mode) goes
raw after ``depth_wait_s``. Pairs go through a bounded queue to the writer, so encoding
and disk never hold up the collector (nor acquisition): when the queue is full the set
is counted in ``skipped_sets``. The writer is two threads: an encoder (frames as zstd row
differences by default, :mod:`app.capture.captureset`, on ``encode_workers`` threads;
``codec="png"`` for PNG) and a store that writes and fsyncs the previous set meanwhile.
Writes are atomic (:mod:`app.capture.recording`).

Faults never kill the service: a write error, a full disk (``ENOSPC``) or a nearly full
one stops the recording, and the reason is kept in ``last_error`` and in ``warning``,
which ``GET /api/status`` carries in its ``warnings`` until the next recording starts;
it is also raised as an alarm (``alarms``), shown on the dashboard until acknowledged.
At construction, recordings a previous run left open are marked ``interrupted`` and
half-written set folders are removed.
"""

from __future__ import annotations

import errno
import io
import logging
import queue
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from app.capture import recording as rec_io
from app.capture.captureset import FRAME_CODECS, CaptureSet, encode_frames
from app.capture.recording import (
    Recording,
    default_name,
    recordings_root,
    recover_interrupted,
    remove_stale_partials,
    validate_name,
)
from app.config import Settings
from app.core.errors import Conflict, InvalidRequest, NotFound
from app.core.limits import DEFAULT_LED
from app.core.schedule import PatternSchedule
from app.service.acquisition import Acquisition
from app.service.alarms import AlarmBoard
from app.service.change import ChangeService
from app.service.framesets import FrameSet
from app.service.reconstruction import LiveResult
from app.service.store import LatestSlot

log = logging.getLogger("fringescope.service.recorder")

SECRET_SETTINGS = frozenset({"api_token"})  # never written to disk


class RecordedInstrument(Protocol):
    """What the recorder reads of the instrument: settings, schedule, whole raw
    sets, published results."""

    @property
    def settings(self) -> Settings: ...
    @property
    def schedule(self) -> PatternSchedule: ...
    @property
    def acquisition(self) -> Acquisition | None: ...
    @property
    def results(self) -> LatestSlot[LiveResult]: ...


class InsufficientDisk(OSError):
    """Too little free space to start or go on recording (HTTP 507)."""


class Recorder:
    """Start/stop recordings of an :class:`~app.service.instrument.Instrument`.

    Args:
        instrument: the live instrument (its ``acquisition`` exists after ``start()``).
        min_free_mb: stop recording when the data folder's disk has less free space, MB.
        depth_wait_s: how long a raw set waits for its depth map before it is written raw, s.
        codec: how frames are stored, ``zstd`` (default) or ``png``.
        queue_sets: sets waiting for the writer at most; one more is counted as skipped.
        encode_workers: threads encoding one set's frames: on a machine shared with other
            work the writer then gets its share of both cores, not of one.
        pose_source: returns the newest received OpenIGTLink TRANSFORMs by device, stored
            with each recorded set (None: no tracker).
        alarms: where a recording that stops on its own is raised as an alarm (None: nowhere).
        changes: the live change service; while it has a reference each set with a depth map
            is stored with its change map Δ (``change.npy``) (None: never).
    """

    def __init__(self, instrument: RecordedInstrument, *, min_free_mb: float = 200.0,
                 depth_wait_s: float = 3.0, codec: str = "zstd", queue_sets: int = 16,
                 encode_workers: int = 2,
                 pose_source: Callable[[], dict[str, Any]] | None = None,
                 alarms: AlarmBoard | None = None,
                 changes: ChangeService | None = None) -> None:
        if codec not in FRAME_CODECS:
            raise ValueError(f"codec: must be one of {FRAME_CODECS}, got {codec!r}")
        if queue_sets < 1:
            raise ValueError(f"queue_sets: must be at least 1, got {queue_sets}")
        if encode_workers < 1:
            raise ValueError(f"encode_workers: must be at least 1, got {encode_workers}")
        self.instrument = instrument
        self.changes = changes
        self.root = recordings_root(instrument.settings.data_dir)
        self.min_free_mb = float(min_free_mb)
        self.depth_wait_s = float(depth_wait_s)
        self.codec = codec
        self.queue_sets = int(queue_sets)
        self.encode_workers = int(encode_workers)
        self._lock = threading.Lock()
        self._recording: Recording | None = None
        self._threads: tuple[threading.Thread, ...] = ()  # collector, encoder, store
        self._stop = threading.Event()
        self._write_failed = threading.Event()
        self.sets_with_depth = 0
        self.skipped_sets = 0
        self.errors = 0
        self.queue_peak = 0
        self.write_cpu_s = 0.0  # the writer's (and its encoders') CPU time this recording, s
        self.encode_wall_s = 0.0  # elapsed time preparing and encoding sets this recording, s
        self.store_wall_s = 0.0  # elapsed time writing them to disk (fsync included), s
        self.sets_written = 0
        self.last_error: str | None = None
        # why the last recording stopped on its own (shown in /api/status warnings)
        self.warning: str | None = None
        # leftovers of a run that ended without closing its recording (kill -9, power cut)
        self.recovered = recover_interrupted(self.root)
        remove_stale_partials(self.root)
        # the newest received OpenIGTLink TRANSFORMs (a tracked scope's pose), by device
        self.pose_source = pose_source
        self.alarms = alarms
        # the dashboard's measurements (kind + pixels), re-measured on every recorded depth map
        self.measurements: list[dict[str, Any]] = []

    # -- control (any thread) --------------------------------------------------------------
    @property
    def active_name(self) -> str | None:
        rec = self._recording
        return rec.name if rec is not None else None

    def start(self, name: str | None = None) -> dict[str, Any]:
        """Begin recording into ``<data_dir>/recordings/<name>`` (default: a time stamp).

        Raises ``Conflict`` if recording or if the name is taken, ``InvalidRequest`` for a
        bad name, ``InsufficientDisk`` when the disk is nearly full.
        """
        if name is not None:
            try:
                validate_name(name, "name")
            except ValueError as exc:
                raise InvalidRequest(str(exc)) from None
        with self._lock:
            if self._recording is not None:
                raise Conflict(f"already recording {self._recording.name!r}: stop it first")
            self._check_disk()
            settings = self.instrument.settings.model_dump(mode="json",
                                                           exclude=set(SECRET_SETTINGS))
            try:
                self._recording = Recording(self.root, name or self._fresh_name(),
                                            settings=settings)
            except FileExistsError as exc:
                raise Conflict(str(exc)) from None
            except ValueError as exc:
                raise InvalidRequest(str(exc)) from None
            self.sets_with_depth = self.skipped_sets = self.errors = self.queue_peak = 0
            self.write_cpu_s, self.sets_written = 0.0, 0
            self.encode_wall_s = self.store_wall_s = 0.0
            self.last_error = self.warning = None
            self._stop.clear()
            self._write_failed.clear()
            jobs: queue.Queue[_Job | None] = queue.Queue(maxsize=self.queue_sets)
            ready: queue.Queue[_Prepared | None] = queue.Queue(maxsize=2)
            rec = self._recording
            self._threads = (
                threading.Thread(target=self._run, args=(rec, jobs), name="fringescope-recorder",
                                 daemon=True),
                threading.Thread(target=self._encode_loop, args=(rec, jobs, ready),
                                 name="fringescope-recorder-encode", daemon=True),
                threading.Thread(target=self._store_loop, args=(rec, ready),
                                 name="fringescope-recorder-store", daemon=True),
            )
            for thread in reversed(self._threads):
                thread.start()
            return self.status()

    def stop(self, timeout_s: float = 30.0) -> dict[str, Any] | None:
        """Finish the running recording (pending sets are written) and return its session."""
        with self._lock:
            rec, threads = self._recording, self._threads
            if rec is None:
                return None
            self._stop.set()
        deadline = time.monotonic() + timeout_s
        for thread in threads:  # the collector hands its last sets over, then the writer drains
            if thread is not threading.current_thread():
                thread.join(max(0.0, deadline - time.monotonic()))
        with self._lock:
            self._recording, self._threads = None, ()
        return rec.close()

    close = stop

    def status(self) -> dict[str, Any]:
        rec = self._recording
        n_sets = rec.n_sets if rec is not None else 0
        return {
            "recording": rec.name if rec is not None else None,
            "sets": n_sets,
            "sets_with_depth": self.sets_with_depth,
            "skipped_sets": self.skipped_sets,
            "errors": self.errors,
            "last_error": self.last_error,
            "queue_peak": self.queue_peak,
            "write_cpu_ms_per_set": round(1e3 * self.write_cpu_s / max(1, self.sets_written), 3),
            # the encoder and the store overlap: the slower of the two bounds the rate
            "write_ms_per_set": round(1e3 * max(self.encode_wall_s, self.store_wall_s)
                                      / max(1, self.sets_written), 3),
        }

    def _fresh_name(self) -> str:
        base = default_name()
        name, n = base, 1
        while (self.root / name).exists():
            n += 1
            name = f"{base}-{n}"
        return name

    def _check_disk(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        free_mb = shutil.disk_usage(self.root).free / 1e6
        if free_mb < self.min_free_mb:
            raise InsufficientDisk(f"only {free_mb:.0f} MB free in {self.root} (need "
                                   f"{self.min_free_mb:.0f} MB)")

    # -- the recordings on disk (NotFound for a name that is not one) -------------------------
    def recordings(self) -> list[dict[str, Any]]:
        """Summaries of every recording in the data folder, by name."""
        return rec_io.list_recordings(self.root)

    def session(self, name: str) -> dict[str, Any]:
        """``session.json`` of recording ``name``."""
        try:
            return rec_io.read_session(self.root, name)
        except FileNotFoundError as exc:
            raise NotFound(str(exc).strip("'\"")) from None
        except ValueError as exc:  # a bad name, or a folder that is not a whole recording
            raise NotFound(f"recording {name!r}: {exc}") from None

    def zip_chunks(self, name: str) -> Iterator[bytes]:
        """The whole recording as a zip, in chunks (NotFound raised before the first chunk)."""
        self.session(name)
        return rec_io.iter_zip(self.root, name)

    def delete(self, name: str) -> None:
        """Delete recording ``name`` (Conflict while it is being written)."""
        if self.active_name == name:
            raise Conflict(f"recording {name!r} is running: stop it first")
        self.session(name)
        try:
            rec_io.delete_recording(self.root, name)
        except FileNotFoundError as exc:
            raise NotFound(str(exc).strip("'\"")) from None

    def set_depth(self, name: str, index: int) -> np.ndarray:
        """The depth map (mm, float32, NaN invalid) of set ``index`` of recording ``name``."""
        session = self.session(name)
        folder = f"set_{index:04d}"
        if not any(s["folder"] == folder for s in session["sets"]):
            raise NotFound(f"recording {name!r} has no set {index}")
        try:  # never through a symbolic link planted in the recording
            data = rec_io.read_set_file(self.root, name, folder, "depth.npy")
        except FileNotFoundError:
            raise NotFound(f"set {index} of {name!r} was recorded without a depth map") from None
        except ValueError as exc:
            raise NotFound(f"set {index} of {name!r} cannot be read: {exc}") from None
        return np.asarray(np.load(io.BytesIO(data), allow_pickle=False))

    def set_capture(self, name: str, index: int) -> CaptureSet:
        """The raw capture set (frames + metadata) of set ``index`` of recording ``name``."""
        from app.capture.captureset import read_capture_set

        session = self.session(name)
        folder = f"set_{index:04d}"
        if not any(s["folder"] == folder for s in session["sets"]):
            raise NotFound(f"recording {name!r} has no set {index}")
        try:
            set_dir = rec_io.safe_child(self.root, name) / folder
            rec_io.check_no_links(set_dir)  # never read through a symbolic link
            return read_capture_set(set_dir)
        except ValueError as exc:
            raise NotFound(f"set {index} of {name!r} cannot be read: {exc}") from None

    # -- the threads ------------------------------------------------------------------------------
    def _run(self, rec: Recording, jobs: queue.Queue[_Job | None]) -> None:
        """Collector: pair each raw set with its depth map, hand it to the writer, never wait.

        It subscribes to both slots, so a set or a map is never missed while this thread
        waits for the CPU: the callbacks (on the acquisition and reconstruction threads)
        only put into ``inbox``.
        """
        inst = self.instrument
        pending: OrderedDict[tuple[float, ...], tuple[FrameSet, float]] = OrderedDict()
        inbox: queue.Queue[FrameSet | LiveResult] = queue.Queue(maxsize=_MAX_INBOX)

        def receive(_seq: int, item: FrameSet | LiveResult) -> None:
            try:
                inbox.put_nowait(item)
            except queue.Full:  # this thread has not run for seconds: counted, never waited on
                self.skipped_sets += isinstance(item, FrameSet)

        def hand_over(fs: FrameSet, res: LiveResult | None) -> None:
            try:
                jobs.put_nowait((fs, res))
            except queue.Full:  # the writer is behind: this set is lost, and counted
                self.skipped_sets += 1
            self.queue_peak = max(self.queue_peak, jobs.qsize())

        unsubscribe = [inst.results.subscribe(receive)]
        watched: Acquisition | None = None
        try:
            while True:
                acq = inst.acquisition
                if acq is not None and acq is not watched:  # started, or restarted
                    unsubscribe.append(acq.sets.subscribe(receive))
                    watched = acq
                shut_down = inst.results.closed or (acq is not None and not acq.alive)
                stopping = self._stop.is_set() or shut_down or self._write_failed.is_set()
                try:
                    item: FrameSet | LiveResult | None = inbox.get(timeout=0.0 if stopping else 0.1)
                except queue.Empty:
                    item = None
                while item is not None:
                    if isinstance(item, LiveResult):
                        self._match(pending, item, hand_over)
                    else:  # (when stopping too: a set taken before the stop is written)
                        pending[tuple(item.timestamps)] = (item, time.monotonic())
                    try:
                        item = inbox.get_nowait()
                    except queue.Empty:
                        item = None
                now = time.monotonic()
                while pending and (stopping
                                   or now - next(iter(pending.values()))[1] > self.depth_wait_s):
                    _, (fs, _) = pending.popitem(last=False)
                    hand_over(fs, None)
                if len(pending) > _MAX_PENDING:  # depth maps stopped coming: the oldest goes raw
                    _, (fs, _) = pending.popitem(last=False)
                    hand_over(fs, None)
                if stopping:
                    break
        except Exception as exc:  # never let a recorder fault escape into the service
            log.exception("recorder failed")
            self._fail(f"recording {rec.name!r} stopped: {exc}", warn=True)
            self._write_failed.set()
        finally:
            for undo in unsubscribe:
                undo()
            jobs.put(None)  # the writer drains what is queued, then ends

    def _encode_loop(self, rec: Recording, jobs: queue.Queue[_Job | None],
                     ready: queue.Queue[_Prepared | None]) -> None:
        """Encoder: build and encode each queued set while the store writes the previous one."""
        try:
            while (job := jobs.get()) is not None:
                if self._write_failed.is_set():
                    continue  # stopped by a fault: what is still queued is not written
                t0, w0 = time.thread_time(), time.perf_counter()
                try:
                    prepared = self._prepare(rec, *job)
                except _StopRecording:
                    self._write_failed.set()
                    continue
                except Exception as exc:  # a bug must not leave the collector without a writer
                    log.exception("recorder encoder failed")
                    self._fail(f"recording {rec.name!r} stopped: {exc}", warn=True)
                    self._write_failed.set()
                    continue
                self.write_cpu_s += time.thread_time() - t0
                self.encode_wall_s += time.perf_counter() - w0
                ready.put(prepared)  # waits while the disk is behind: ``jobs`` fills meanwhile
        finally:
            ready.put(None)

    def _store_loop(self, rec: Recording, ready: queue.Queue[_Prepared | None]) -> None:
        """Store: write each encoded set to disk in order; it finishes the recording."""
        try:
            while (prepared := ready.get()) is not None:
                if self._write_failed.is_set():
                    continue
                t0, w0 = time.thread_time(), time.perf_counter()
                try:
                    self._store(rec, prepared)
                except _StopRecording:
                    self._write_failed.set()
                except Exception as exc:
                    log.exception("recorder store failed")
                    self._fail(f"recording {rec.name!r} stopped: {exc}", warn=True)
                    self._write_failed.set()
                self.write_cpu_s += time.thread_time() - t0
                self.store_wall_s += time.perf_counter() - w0
        finally:
            if self._recording is rec and not self._stop.is_set():
                # stopped on its own (fault, disk full, instrument shut down): finish the session
                with self._lock:
                    self._recording, self._threads = None, ()
                try:
                    rec.close()
                except OSError as exc:  # no room for session.json: marked interrupted at next start
                    log.warning("recording %r could not be closed: %s", rec.name, exc)

    @staticmethod
    def _match(pending: OrderedDict[tuple[float, ...], tuple[FrameSet, float]], res: LiveResult,
               hand_over: Callable[[FrameSet, LiveResult | None], None]) -> None:
        key = tuple(res.timestamps)
        if key not in pending:
            return
        # sets older than the reconstructed one were skipped by reconstruction: written raw
        while pending:
            k, (fs, _) = pending.popitem(last=False)
            hand_over(fs, res if k == key else None)
            if k == key:
                break

    def _prepare(self, rec: Recording, fs: FrameSet, res: LiveResult | None) -> _Prepared:
        """A set ready for the disk: its capture set with metadata and measurements, encoded."""
        pool_cpu: list[float] = []  # the encoder threads' CPU, counted with the writer's
        try:
            self._check_disk()
            now_wall, now_mono = time.time(), time.monotonic()
            capture = CaptureSet(
                frames=fs.stack(), schedule=self.instrument.schedule,
                exposure_ms=float(fs.exposure_ms), led=fs.led or DEFAULT_LED,
                extra={"frame_indices": fs.frame_indices, "mode": fs.mode},
                bit_depth=self.instrument.settings.bit_depth,
            )
            info: dict[str, Any] = {"frame_indices": fs.frame_indices, "depth": res is not None}
            poses = self.pose_source() if self.pose_source is not None else None
            if poses:  # stored in capture.json and session.json
                capture.extra["igtl_transforms"] = poses
                info["igtl_transforms"] = poses
            if res is not None:
                info.update(result_seq=res.seq, latency_ms=round(res.latency_ms, 3),
                            valid_fraction=round(float(res.valid.mean()), 6))
                specs = list(self.measurements)
                if specs:  # the dashboard's measurements on this set's depth map
                    from app.service.measure import calibration_terms, measure_specs

                    calibration = getattr(self.instrument, "calibration", None)
                    normal, cal_sigma, cal_length = calibration_terms(calibration)
                    try:
                        measured = measure_specs(res, specs, normal, cal_sigma, cal_length)
                    except Exception:  # a measurement fault must not stop the recording
                        log.exception("measurements of a recorded set failed")
                        measured = []
                    # a measurement refused on this map (too few valid pixels) is not a value
                    measured = [m for m in measured if "error" not in m]
                    if measured:
                        info["measurements"] = capture.extra["measurements"] = measured
            encoded = encode_frames(capture.frames, self.codec, self.encode_workers, pool_cpu)
        except (OSError, ValueError) as exc:
            raise self._stopped(rec, exc) from exc
        if self.encode_workers > 1:
            self.write_cpu_s += sum(pool_cpu)
        change_mm = None
        changes = self.changes
        if res is not None and changes is not None and changes.store.reference is not None:
            live = changes.change_for(res.seq, CHANGE_WAIT_S)  # its own thread made it
            info["change"] = "none" if live is None else live.result.mode
            change_mm = None if live is None else live.result.cmap.delta
        return _Prepared(capture, None if res is None else res.depth,
                         now_wall - (now_mono - fs.received_s), info, encoded, change_mm)

    def _store(self, rec: Recording, p: _Prepared) -> None:
        try:
            self._check_disk()
            rec.add_set(p.capture, depth_mm=p.depth_mm, timestamp=p.timestamp, info=p.info,
                        codec=self.codec, encoded=p.encoded, change_mm=p.change_mm)
        except (OSError, ValueError) as exc:
            raise self._stopped(rec, exc) from exc
        self.sets_with_depth += p.depth_mm is not None
        self.sets_written += 1

    def _stopped(self, rec: Recording, exc: Exception) -> _StopRecording:
        full = isinstance(exc, InsufficientDisk) or getattr(exc, "errno", None) == errno.ENOSPC
        reason = f"disk full ({exc})" if full else str(exc)
        self._fail(f"recording {rec.name!r} stopped after {rec.n_sets} sets: {reason}", warn=True)
        return _StopRecording()

    def _fail(self, msg: str, *, warn: bool = False) -> None:
        log.warning("%s", msg)
        self.errors += 1
        self.last_error = msg
        if warn:
            self.warning = msg
            if self.alarms is not None:
                self.alarms.raise_alarm("recorder", msg)


# raw sets waiting for their depth map; depth_wait_s (3 s) holds about 11 of geometric-9's
_MAX_PENDING = 16
#: how long a recorded set waits for its change map (the change thread makes it; a registered
#: one can take longer: the set is then written without change.npy, info "change": "none")
CHANGE_WAIT_S = 1.0
_MAX_INBOX = 64  # sets and maps the collector has not looked at yet
_Job = tuple[FrameSet, "LiveResult | None"]


@dataclass(frozen=True)
class _Prepared:
    """A set between the encoder and the store."""

    capture: CaptureSet
    depth_mm: np.ndarray | None
    timestamp: float
    info: dict[str, Any]
    encoded: list[bytes]
    change_mm: np.ndarray | None = None  # Δ against the change reference, mm (change.npy)


class _StopRecording(Exception):
    pass
