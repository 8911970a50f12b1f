"""Recording the live instrument: every whole fringe set to disk, with its depth map.

A recorder thread follows two public slots of the Instrument: ``acquisition.sets``
(each whole raw set, as grabbed) and ``results`` (each published depth map). A raw set
is written with the depth map reconstructed from it (matched by the frames' timestamps);
a set the reconstruction skipped (newest-wins queue, no calibration, rolling mode) is
written raw after ``depth_wait_s``. Writes are atomic (:mod:`app.capture.recording`).

Faults never kill the service: a write error or a nearly full disk stops the recording
and is reported (``last_error``); sets the writer could not keep up with are counted
(``skipped_sets``).
"""

from __future__ import annotations

import io
import logging
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any, Protocol

import numpy as np

from app.capture import recording as rec_io
from app.capture.captureset import CaptureSet
from app.capture.recording import (
    Recording,
    default_name,
    recordings_root,
    remove_stale_partials,
    validate_name,
)
from app.config import Settings
from app.core.errors import Conflict, InvalidRequest, NotFound
from app.core.schedule import PatternSchedule
from app.service.acquisition import Acquisition
from app.service.framesets import FrameSet
from app.service.reconstruction import LiveResult
from app.service.store import LatestSlot

log = logging.getLogger("fringescope.service.recorder")

SECRET_SETTINGS = frozenset({"api_token"})  # never written to disk


class RecordedInstrument(Protocol):
    """What the recorder reads of the instrument: settings, schedule, whole raw sets, published results."""

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
    """

    def __init__(self, instrument: RecordedInstrument, *, min_free_mb: float = 200.0, depth_wait_s: float = 3.0) -> None:
        self.instrument = instrument
        self.root = recordings_root(instrument.settings.data_dir)
        self.min_free_mb = float(min_free_mb)
        self.depth_wait_s = float(depth_wait_s)
        self._lock = threading.Lock()
        self._recording: Recording | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.sets_with_depth = 0
        self.skipped_sets = 0
        self.errors = 0
        self.last_error: str | None = None
        self._cleaned = False
        # issue 16: the newest received OpenIGTLink TRANSFORMs (a tracked scope's pose), by device
        self.pose_source: Callable[[], dict[str, Any]] | None = None
        # issue 17: the dashboard's measurements (kind + pixels), re-measured on every recorded depth map
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
            if not self._cleaned:
                remove_stale_partials(self.root)  # leftovers of a crash before this start
                self._cleaned = True
            self._check_disk()
            settings = self.instrument.settings.model_dump(mode="json", exclude=set(SECRET_SETTINGS))
            try:
                self._recording = Recording(self.root, name or self._fresh_name(), settings=settings)
            except FileExistsError as exc:
                raise Conflict(str(exc)) from None
            except ValueError as exc:
                raise InvalidRequest(str(exc)) from None
            self.sets_with_depth = self.skipped_sets = self.errors = 0
            self.last_error = None
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, args=(self._recording,),
                                            name="fringescope-recorder", daemon=True)
            self._thread.start()
            return self.status()

    def stop(self, timeout_s: float = 30.0) -> dict[str, Any] | None:
        """Finish the running recording (pending sets are written) and return its session."""
        with self._lock:
            rec, thread = self._recording, self._thread
            if rec is None:
                return None
            self._stop.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
        with self._lock:
            self._recording, self._thread = None, None
        return rec.close()

    close = stop

    def status(self) -> dict[str, Any]:
        rec = self._recording
        return {
            "recording": rec.name if rec is not None else None,
            "sets": rec.n_sets if rec is not None else 0,
            "sets_with_depth": self.sets_with_depth,
            "skipped_sets": self.skipped_sets,
            "errors": self.errors,
            "last_error": self.last_error,
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
            raise InsufficientDisk(f"only {free_mb:.0f} MB free in {self.root} (need {self.min_free_mb:.0f} MB)")

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

    # -- the thread ------------------------------------------------------------------------------
    def _run(self, rec: Recording) -> None:
        inst = self.instrument
        pending: OrderedDict[tuple[float, ...], tuple[FrameSet, float]] = OrderedDict()
        set_seq = result_seq = -1
        try:
            while True:
                acq = inst.acquisition
                shut_down = inst.results.closed or (acq is not None and not acq.alive)
                stopping = self._stop.is_set() or shut_down
                if acq is not None and not stopping:
                    if set_seq < 0:
                        set_seq = acq.sets.seq  # record from now on, not the set before start
                    seq, fs = acq.sets.wait_newer(set_seq, 0.1)
                    if fs is not None:
                        self.skipped_sets += max(0, seq - set_seq - 1)
                        set_seq = seq
                        pending[tuple(fs.timestamps)] = (fs, time.monotonic())
                elif not stopping:
                    self._stop.wait(0.1)
                seq, res = inst.results.latest()
                if res is not None and seq != result_seq:
                    result_seq = seq
                    self._match(rec, pending, res)
                now = time.monotonic()
                while pending and (stopping or now - next(iter(pending.values()))[1] > self.depth_wait_s):
                    _, (fs, _) = pending.popitem(last=False)
                    self._write(rec, fs, None)
                if len(pending) > 8:  # the writer cannot keep up: drop the oldest, counted
                    pending.popitem(last=False)
                    self.skipped_sets += 1
                if stopping:
                    break
        except _StopRecording:
            pass
        except Exception as exc:  # never let a recorder fault escape into the service
            log.exception("recorder failed")
            self._fail(f"recording stopped: {exc}")
        finally:
            if self._recording is rec and not self._stop.is_set():
                # stopped on its own (fault, disk full, instrument shut down): finish the session
                with self._lock:
                    self._recording, self._thread = None, None
                rec.close()

    def _match(self, rec: Recording, pending: OrderedDict[tuple[float, ...], tuple[FrameSet, float]],
               res: LiveResult) -> None:
        key = tuple(res.timestamps)
        if key not in pending:
            return
        # sets older than the reconstructed one were skipped by reconstruction: write raw
        while pending:
            k, (fs, _) = pending.popitem(last=False)
            self._write(rec, fs, res if k == key else None)
            if k == key:
                break

    def _write(self, rec: Recording, fs: FrameSet, res: LiveResult | None) -> None:
        try:
            self._check_disk()
            now_wall, now_mono = time.time(), time.monotonic()
            capture = CaptureSet(
                frames=fs.stack(), schedule=self.instrument.schedule, exposure_ms=float(fs.exposure_ms),
                led=fs.led or "green", extra={"frame_indices": fs.frame_indices, "mode": fs.mode},
                bit_depth=self.instrument.settings.bit_depth,
            )
            info: dict[str, Any] = {"frame_indices": fs.frame_indices, "depth": res is not None}
            poses = self.pose_source() if self.pose_source is not None else None
            if poses:  # issue 16: stored in capture.json and session.json
                capture.extra["igtl_transforms"] = poses
                info["igtl_transforms"] = poses
            if res is not None:
                info.update(result_seq=res.seq, latency_ms=round(res.latency_ms, 3),
                            valid_fraction=round(float(res.valid.mean()), 6))
                specs = list(self.measurements)
                if specs:  # issue 17: the dashboard's measurements on this set's depth map
                    from app.service.measure import calibration_terms, measure_specs

                    normal, cal_sigma, cal_length = calibration_terms(getattr(self.instrument, "calibration", None))
                    try:
                        info["measurements"] = measure_specs(res, specs, normal, cal_sigma, cal_length)
                    except Exception as exc:  # a measurement fault must not stop the recording
                        log.exception("measurements of a recorded set failed")
                        info["measurements"] = [{"error": f"measurement failed: {exc}"}]
                    capture.extra["measurements"] = info["measurements"]
            rec.add_set(capture, depth_mm=None if res is None else res.depth,
                        timestamp=now_wall - (now_mono - fs.received_s), info=info)
        except (OSError, ValueError) as exc:
            self._fail(f"recording stopped: {exc}")
            raise _StopRecording from exc
        self.sets_with_depth += res is not None

    def _fail(self, msg: str) -> None:
        log.warning("%s", msg)
        self.errors += 1
        self.last_error = msg


class _StopRecording(Exception):
    pass
