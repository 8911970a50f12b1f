"""The Instrument: devices, the acquisition and reconstruction threads, the latest result.

Everything the API does goes through here. Threads stop on events and are joined in
:meth:`Instrument.close`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

from app.calib.calibration import Calibration, save_calibration
from app.capture.captureset import CaptureSet
from app.config import Settings
from app.devices.base import EXPOSURE_RANGE_MS, LEDS
from app.recon.patterns import PatternSchedule
from app.service import calibration_store
from app.service.autoexposure import AutoExposureResult, choose_exposure, set_statistics
from app.service.calibration_session import CalibrationSession
from app.service.devices import DeviceBundle, create_devices
from app.service.framesets import FrameSet
from app.service.reconstruction import LiveResult, Reconstruction
from app.service.store import NewestQueue

log = logging.getLogger("fringescope.service")


class NotReady(RuntimeError):
    """The instrument cannot do this yet (no result, no calibration, no session); → 503/404."""


class Instrument:
    """The live instrument built from ``settings``; ``start()`` then ``close()``."""

    def __init__(self, settings: Settings, *, devices: DeviceBundle | None = None) -> None:
        self.settings = settings
        self.schedule = PatternSchedule()
        self.devices = devices
        self.queue: NewestQueue[FrameSet] = NewestQueue(maxsize=1)
        self.acquisition: Any = None
        self.reconstruction = Reconstruction(
            self.queue, self._live_engine, n_frequencies=len(self.schedule.frequencies),
            bit_depth=settings.bit_depth,
        )
        self.results = self.reconstruction.results
        self.store = self.results  # the viewer's name for the latest-result slot
        self.calibration: Calibration | None = None
        self.recorder: Any = None  # the Recorder of live sets, attached by create_app
        self.calibration_name: str | None = None
        self.session: CalibrationSession | None = None
        self.warnings: list[str] = []
        self.last_error: str | None = None
        self._engine: Any = None
        self._upload_engine: Any = None
        self._upload_engine_cal: Calibration | None = None
        self._upload_lock = threading.Lock()
        self._control_lock = threading.Lock()
        self._calibrating: threading.Thread | None = None
        self._closed = False
        self._started = False

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> None:
        """Create the devices, start both threads, and load (or begin creating) a calibration."""
        from app.service.acquisition import Acquisition

        if self._started:
            return
        self._started = True
        if self.devices is None:
            self.devices = create_devices(self.settings)
        self.acquisition = Acquisition(
            self.devices, self.schedule, self.queue,
            exposure_ms=self.settings.exposure_ms, led=self.settings.led,
            bit_depth=self.settings.bit_depth, rolling=self.settings.rolling,
        )
        self._load_initial_calibration()
        self.reconstruction.start_thread()
        self.acquisition.start_thread(acquire=self.settings.autostart)

    def close(self, timeout_s: float = 15.0) -> None:
        """Stop and join every thread, close the devices (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self.acquisition is not None:
            self.acquisition.shutdown(timeout_s)
        self.reconstruction.shutdown(timeout_s)
        if self._calibrating is not None and self._calibrating.is_alive():
            self._calibrating.join(max(timeout_s, 120.0))  # a fit cannot be interrupted

    stop = close

    def threads(self) -> list[threading.Thread]:
        """The instrument's own threads (for shutdown checks)."""
        out = [self.reconstruction._thread]
        if self.acquisition is not None:
            out.append(self.acquisition._thread)
        if self._calibrating is not None:
            out.append(self._calibrating)
        return out

    # -- calibration -------------------------------------------------------------------
    def _load_initial_calibration(self) -> None:
        s = self.settings
        try:
            path = calibration_store.initial_path(s)
        except ValueError as exc:
            self._error(str(exc))
            return
        if path is not None:
            try:
                cal = calibration_store.load(path)
                name = str(cal.extra.get(calibration_store.NAME_KEY, path.stem))
                self.set_calibration(cal, name=name, persist=False)
                return
            except ValueError as exc:
                self._error(str(exc))
                if s.calibration_file is not None:
                    return
        if self.devices is not None and self.devices.is_sim:
            self._calibrating = threading.Thread(
                target=self._create_sim_calibration, name="fringescope-calibrate", daemon=True
            )
            self._calibrating.start()
        else:
            self.warnings.append("no calibration: load one (PUT /api/calibration/file) or calibrate")

    def _create_sim_calibration(self) -> None:
        try:
            cal = calibration_store.create_sim_calibration(self.settings)
        except Exception as exc:
            log.exception("simulator calibration failed")
            self._error(f"simulator calibration failed: {exc}")
            return
        if not self._closed:
            self.set_calibration(cal, name="sim", persist=False)

    def set_calibration(self, cal: Calibration, *, name: str, persist: bool = True) -> None:
        """Make ``cal`` active for live and uploaded sets (saved as the active one if ``persist``)."""
        from app.recon import Reconstructor
        from app.recon.patterns import check_pattern

        check_pattern(cal.pattern, self.schedule, "projector")  # names orientation/unwrap mismatches
        if cal.pattern != self.schedule:
            raise ValueError("calibration: its pattern schedule differs from the projector's")
        if self.devices is not None:
            caps = self.devices.camera.capabilities
            if tuple(cal.image_size) != (caps.width, caps.height):
                raise ValueError(
                    f"calibration: image size {cal.image_size[0]}x{cal.image_size[1]} does not match "
                    f"the camera's {caps.width}x{caps.height}"
                )
        bits = self.settings.bit_depth
        engine = Reconstructor(cal, fast=True, max_code=None if bits == 8 else 2**bits - 1)
        if persist:
            calibration_store.save_active(self.settings, cal, name)
        with self._control_lock:
            self.calibration, self.calibration_name = cal, name
            self._engine = engine
            self._upload_engine = None
            self.warnings = [w for w in self.warnings if not w.startswith("no calibration")]
        self.results.clear()

    def calibration_summary(self) -> dict[str, Any] | None:
        cal = self.calibration
        if cal is None:
            return None
        return {
            "name": self.calibration_name, "created": cal.created,
            "height_range_mm": list(cal.height_range_mm), "image_size": list(cal.image_size),
            "software_version": cal.software_version, "poses": len(cal.pose_residuals),
            "model": cal.model.name, "held_out": cal.held_out,
        }

    @property
    def calibrating(self) -> bool:
        return self._calibrating is not None and self._calibrating.is_alive()

    def _live_engine(self) -> Any:
        return self._engine

    # -- control ---------------------------------------------------------------------------
    def set_exposure(self, exposure_ms: float) -> float:
        lo, hi = EXPOSURE_RANGE_MS
        if not (math.isfinite(exposure_ms) and lo <= exposure_ms <= hi):
            raise ValueError(f"exposure_ms: must be within {lo}–{hi} ms, got {exposure_ms}")
        self._acq().request(exposure_ms=float(exposure_ms))
        return float(exposure_ms)

    def set_led(self, led: str) -> str:
        if led not in LEDS:
            raise ValueError(f"led: must be one of {LEDS}, got {led!r}")
        self._acq().request(led=led)
        return led

    def set_rolling(self, rolling: bool) -> None:
        self._acq().set_rolling(rolling)

    def set_acquiring(self, on: bool) -> None:
        self._acq().set_acquiring(on)

    def _acq(self) -> Any:
        if self.acquisition is None:
            raise NotReady("instrument not started")
        return self.acquisition

    # -- results -----------------------------------------------------------------------------
    def latest_result(self) -> LiveResult:
        _, res = self.results.latest()
        if res is None:
            raise NotReady(self._why_no_result())
        return res

    def wait_result(self, after_seq: int, timeout_s: float) -> LiveResult | None:
        """The first result newer than ``after_seq`` (None on timeout or shutdown)."""
        return self.results.wait_newer(after_seq, timeout_s)[1]

    def _why_no_result(self) -> str:
        if self.calibrating:
            return "no depth result yet: the calibration is being created"
        if self.calibration is None:
            return "no depth result: no calibration is active"
        if self.acquisition is None or not self.acquisition.acquiring:
            return "no depth result: acquisition is stopped"
        if self.acquisition.fault:
            return f"no depth result: device fault ({self.acquisition.fault})"
        return "no depth result yet"

    def next_capture(self, timeout_s: float = 10.0, *, exposure_ms: float | None = None) -> CaptureSet:
        """The next whole fringe set grabbed after this call (optionally at one exposure)."""
        acq = self._acq()
        if not acq.acquiring:
            raise NotReady("acquisition is stopped: start it to capture")
        seq = acq.sets.seq
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            seq, fs = acq.sets.wait_newer(seq, left)
            if fs is None:
                break
            if exposure_ms is None or abs(fs.exposure_ms - exposure_ms) <= 1e-3 * exposure_ms + 1e-3:
                return CaptureSet(fs.stack(), self.schedule, float(fs.exposure_ms), fs.led or "green",
                                  bit_depth=self.settings.bit_depth,
                                  extra={"frame_indices": fs.frame_indices})
        raise NotReady(f"no complete fringe set within {timeout_s:.0f} s")

    def reconstruct_capture(self, capture: CaptureSet) -> Any:
        """Reconstruct an uploaded set with the active calibration (its own engine instance)."""
        from app.recon import Reconstructor
        from app.recon.patterns import check_pattern

        cal = self.calibration
        if cal is None:
            raise NotReady("no calibration is active")
        check_pattern(cal.pattern, capture.schedule)
        if capture.schedule != cal.pattern:
            raise ValueError("capture: pattern schedule differs from the calibration's")
        cal.check_frames(capture.frames.shape)
        with self._upload_lock:
            if self._upload_engine is None or self._upload_engine_cal is not cal:
                self._upload_engine = Reconstructor(cal, fast=True)
                self._upload_engine_cal = cal
            return self._upload_engine.run(capture.frames, max_code=capture.max_code)

    def auto_exposure(self, *, saturation_limit: float = 0.005, max_exposure_ms: float = 100.0) -> AutoExposureResult:
        """Search exposures on real sets, then keep the chosen one."""
        acq = self._acq()
        before = acq.exposure_ms
        full_scale = 255 if self.settings.bit_depth == 8 else 2**self.settings.bit_depth - 1

        def measure(exposure_ms: float) -> tuple[float, float]:
            self.set_exposure(exposure_ms)
            timeout = 5.0 + 3 * self.schedule.n_frames * max(exposure_ms, 30.0) / 1000.0
            cap = self.next_capture(timeout, exposure_ms=exposure_ms)
            frames = cap.frames
            fs = 255 if frames.dtype.itemsize == 1 else full_scale
            return set_statistics(frames, self.schedule, fs)

        try:
            result = choose_exposure(measure, saturation_limit=saturation_limit, max_exposure_ms=max_exposure_ms)
        except Exception:
            self.set_exposure(before)
            raise
        self.set_exposure(result.exposure_ms)
        return result

    # -- status ----------------------------------------------------------------------------------
    def state(self) -> str:
        """starting | calibrating | running | stopped | fault (a fault outranks the rest)."""
        acq = self.acquisition
        if self._closed:
            return "stopped"
        if acq is None:
            return "starting"
        if acq.acquiring and (acq.fault or (self.devices is not None and self.devices.faulted())):
            return "fault"
        if self.calibrating:
            return "calibrating"
        if not acq.acquiring:
            return "stopped"
        if acq.frames_received == 0 or (self.calibration is not None and self.results.seq == 0):
            return "starting"
        return "running"

    def status(self) -> dict[str, Any]:
        acq, rec = self.acquisition, self.reconstruction
        latency = rec.latencies.median()
        warnings = list(self.warnings)
        if acq is not None and not acq.assembler.completed and acq.frames_received > 3 * self.schedule.n_frames:
            warnings.append("no complete fringe set in the frames so far (missing pattern indices or drops)")
        last_error = self.last_error
        for err in (acq.last_error if acq else None, rec.last_error):
            if err:
                last_error = err
        return {
            "state": self.state(),
            "camera_fps": round(acq.camera_rate.rate(), 3) if acq else 0.0,
            "depth_fps": round(rec.depth_rate.rate(), 3),
            "latency_ms": None if latency is None else round(latency, 3),
            "recon_ms": None if (recon := rec.recon_times.median()) is None else round(recon, 3),
            "exposure_ms": acq.exposure_ms if acq else self.settings.exposure_ms,
            "led": acq.led if acq else self.settings.led,
            "mode": "rolling" if (acq.rolling if acq else self.settings.rolling) else "set",
            "acquiring": bool(acq and acq.acquiring),
            "calibration": self.calibration_summary(),
            "devices": self.devices.describe() if self.devices is not None else [],
            "last_error": last_error,
            "sets_completed": acq.assembler.completed if acq else 0,
            "results_published": rec.completed,
            "dropped_sets": self.queue.dropped,
            "incomplete_sets": acq.assembler.incomplete if acq else 0,
            "mixed_sets": acq.assembler.mixed if acq else 0,
            "frames_received": acq.frames_received if acq else 0,
            "frames_dropped": acq.frames_dropped if acq else 0,
            "faults": acq.faults if acq else 0,
            "recording": getattr(self.recorder, "active_name", None),
            "bit_depth": self.settings.bit_depth,
            "schedule": self.schedule.to_dict(),
            "warnings": warnings,
        }

    def _error(self, msg: str) -> None:
        log.warning("%s", msg)
        self.last_error = msg
        self.warnings.append(msg)

    # -- calibration session -------------------------------------------------------------------
    def calibration_dir(self) -> Path:
        return Path(self.settings.data_dir) / "calibrations"

    def save_calibration_copy(self, cal: Calibration, name: str) -> Path:
        return save_calibration(cal, self.calibration_dir() / f"{name}.json")

    # -- calibration session (the REST wizard) ---------------------------------------------
    def start_session(self, board: dict[str, Any]) -> CalibrationSession:
        from app.calib.board import BoardSpec

        self.session = CalibrationSession(BoardSpec.from_dict(board))
        return self.session

    def require_session(self) -> CalibrationSession:
        if self.session is None:
            raise NotReady("no calibration session: POST /api/calibration/session first")
        return self.session

    def capture_pose(self, timeout_s: float = 15.0) -> dict[str, Any]:
        """Grab the next whole set of the current view and add it to the session."""
        session = self.require_session()
        index, pose = session.add(self.next_capture(timeout_s))
        return {**pose.summary(index), "corner_points": pose.detection.image_points.tolist()}

    def solve_session(self, *, robust: bool = False) -> Any:
        return self.require_session().solve(robust=robust)

    def activate_session(self, name: str) -> dict[str, Any]:
        session = self.require_session()
        if session.report is None:
            raise NotReady("calibration session not solved: POST /api/calibration/session/solve first")
        self.set_calibration(session.report.calibration, name=name, persist=True)
        summary = self.calibration_summary()
        assert summary is not None
        return summary
