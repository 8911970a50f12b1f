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

import logging
import shutil
import threading
import time
from collections import OrderedDict
from typing import Any

from app.capture.captureset import CaptureSet
from app.capture.recording import (
    Recording,
    default_name,
    recordings_root,
    remove_stale_partials,
    validate_name,
)
from app.service.framesets import FrameSet
from app.service.reconstruction import LiveResult

log = logging.getLogger("fringescope.service.recorder")

SECRET_SETTINGS = frozenset({"api_token"})  # never written to disk


class RecorderBusy(RuntimeError):
    """A recording is already running (→ HTTP 409)."""


class Recorder:
    """Start/stop recordings of an :class:`~app.service.instrument.Instrument`.

    Args:
        instrument: the live instrument (its ``acquisition`` exists after ``start()``).
        min_free_mb: stop recording when the data folder's disk has less free space, MB.
        depth_wait_s: how long a raw set waits for its depth map before it is written raw, s.
    """

    def __init__(self, instrument: Any, *, min_free_mb: float = 200.0, depth_wait_s: float = 3.0) -> None:
        self.instrument = instrument
        self.root = recordings_root(instrument.settings.data_dir)
        self.min_free_mb = float(min_free_mb)
        self.depth_wait_s = float(depth_wait_s)
        self._lock = threading.Lock()
        self._recording: Recording | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.sets_written = 0
        self.sets_with_depth = 0
        self.skipped_sets = 0
        self.errors = 0
        self.last_error: str | None = None
        self._cleaned = False

    # -- control (any thread) --------------------------------------------------------------
    @property
    def active_name(self) -> str | None:
        rec = self._recording
        return rec.name if rec is not None else None

    def start(self, name: str | None = None) -> dict[str, Any]:
        """Begin recording into ``<data_dir>/recordings/<name>`` (default: a time stamp).

        Raises ``RecorderBusy`` if recording, ``FileExistsError`` if the name is taken,
        ``ValueError`` for a bad name.
        """
        if name is not None:
            validate_name(name, "name")
        with self._lock:
            if self._recording is not None:
                raise RecorderBusy(f"already recording {self._recording.name!r}: stop it first")
            if not self._cleaned:
                remove_stale_partials(self.root)  # leftovers of a crash before this start
                self._cleaned = True
            self._check_disk()
            settings = self.instrument.settings.model_dump(mode="json", exclude=set(SECRET_SETTINGS))
            self._recording = Recording(self.root, name or self._fresh_name(), settings=settings)
            self.sets_written = self.sets_with_depth = self.skipped_sets = self.errors = 0
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
            raise OSError(f"only {free_mb:.0f} MB free in {self.root} (need {self.min_free_mb:.0f} MB)")

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
            if res is not None:
                info.update(result_seq=res.seq, latency_ms=round(res.latency_ms, 3),
                            valid_fraction=round(float(res.valid.mean()), 6))
            rec.add_set(capture, depth_mm=None if res is None else res.depth,
                        timestamp=now_wall - (now_mono - fs.received_s), info=info)
        except (OSError, ValueError) as exc:
            self._fail(f"recording stopped: {exc}")
            raise _StopRecording from exc
        self.sets_written += 1
        self.sets_with_depth += res is not None

    def _fail(self, msg: str) -> None:
        log.warning("%s", msg)
        self.errors += 1
        self.last_error = msg


class _StopRecording(Exception):
    pass
