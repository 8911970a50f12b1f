"""The live pipeline: devices → acquisition thread → reconstruction thread → latest result.

It reconstructs with whichever engine the calibration manager installs
(:meth:`LivePipeline.use_engine`); without one, whole sets are grabbed but not
reconstructed. Threads stop on events and are joined in :meth:`LivePipeline.close`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.capture.captureset import CaptureSet
from app.core.errors import Conflict, DeviceUnavailable, InvalidRequest
from app.core.limits import DEFAULT_LED, EXPOSURE_RANGE_MS, LEDS, full_scale
from app.core.reasons import Reason
from app.core.schedule import PatternSchedule
from app.recon import Reconstructor
from app.recon.exposure import (
    DEFAULT_SATURATION_LIMIT,
    AutoExposureResult,
    bracket_exposures,
    choose_exposure,
    set_statistics,
)
from app.recon.motion import (
    DEFAULT_FALSE_ALARM_RATE,
    DEFAULT_GROW_PX,
    DEFAULT_WINDOW_PX,
    MotionTest,
)
from app.recon.validity import DEFAULT_GROSS_ERROR_MM
from app.service.acquisition import Acquisition
from app.service.devices import DeviceBundle
from app.service.framesets import FrameSet
from app.service.reconstruction import LiveResult, Reconstruction
from app.service.store import LatestSlot, NewestQueue

#: share of a scene's lit, unsaturated pixels invalid for low signal at the auto exposure beyond
#: which the auto-exposure switches exposure bracketing on
BRACKET_DIM_SHARE = 0.10


@dataclass(frozen=True)
class PipelineConfig:
    """What the pipeline needs of the settings: the starting acquisition parameters."""

    exposure_ms: float
    led: str
    bit_depth: int
    rolling: bool
    autostart: bool
    motion_false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE  # over the image, per map
    motion_grow_px: int = DEFAULT_GROW_PX
    motion_window_px: int = DEFAULT_WINDOW_PX
    gross_error_mm: float | None = DEFAULT_GROSS_ERROR_MM  # None: no σ bound while moving
    noise_estimate_interval_s: float = 30.0  # the camera's noise measured this often (0: nominal)


class LivePipeline:
    """Devices, the acquisition and reconstruction threads, the latest result."""

    def __init__(self, config: PipelineConfig, schedule: PatternSchedule,
                 devices: DeviceBundle | None) -> None:
        self.config = config
        self.schedule = schedule
        self.devices = devices
        self.queue: NewestQueue[FrameSet] = NewestQueue(maxsize=1)
        self.acquisition: Acquisition | None = None
        motion = MotionTest(false_alarm_rate=config.motion_false_alarm_rate,
                            window_px=config.motion_window_px, grow_px=config.motion_grow_px,
                            gross_error_mm=config.gross_error_mm)
        self.reconstruction = Reconstruction(
            self.queue, self._live_engine, bit_depth=config.bit_depth, motion=motion,
            noise_estimate_interval_s=config.noise_estimate_interval_s,
        )
        self.results: LatestSlot[LiveResult] = self.reconstruction.results
        self._engine: Reconstructor | None = None
        # why there is no engine although a calibration is loaded
        self.engine_note: str | None = None
        self.closed = False
        self.bracket_auto = False  # bracketing was switched on by the auto-exposure
        self.bracket_dim_share: float | None = None  # the auto-exposure's last judgement

    # -- lifecycle -------------------------------------------------------------------------
    def start(self, devices: DeviceBundle) -> None:
        """Take ``devices`` and build the acquisition on them; the threads start in :meth:`run`."""
        self.devices = devices
        c = self.config
        self.acquisition = Acquisition(
            devices, self.schedule, self.queue,
            exposure_ms=c.exposure_ms, led=c.led, bit_depth=c.bit_depth, rolling=c.rolling,
        )

    def run(self) -> None:
        """Start the reconstruction and acquisition threads (acquiring if ``autostart``)."""
        self.reconstruction.start_thread()
        self._acq().start_thread(acquire=self.config.autostart)

    def close(self, timeout_s: float) -> None:
        self.closed = True
        if self.acquisition is not None:
            self.acquisition.shutdown(timeout_s)
        self.reconstruction.shutdown(timeout_s)

    def threads(self) -> list[threading.Thread]:
        out = [self.reconstruction._thread]
        if self.acquisition is not None:
            out.append(self.acquisition._thread)
        return out

    # -- the engine ------------------------------------------------------------------------
    def use_engine(self, engine: Reconstructor | None, note: str | None = None) -> None:
        """Reconstruct from now on with ``engine`` (None: not at all, because of ``note``);
        older results are dropped."""
        self._engine = engine
        self.engine_note = note if engine is None else None
        self.results.clear()

    def set_schedule(self, schedule: PatternSchedule,
                     engine_for: Callable[[PatternSchedule],
                                          tuple[Reconstructor | None, str | None]],
                     timeout_s: float = 10.0) -> None:
        """Run ``schedule`` from the next set boundary, reconstructing with
        ``engine_for(schedule)``.

        The engine is built first (it takes a moment); the acquisition then swaps the schedule
        between two sets, installs the engine, and reloads the devices' patterns.

        Raises:
            DeviceUnavailable: the acquisition did not reach a set boundary within ``timeout_s``.
        """
        if schedule == self.schedule:
            return
        engine, note = engine_for(schedule)

        def swap(new: PatternSchedule) -> None:
            self.schedule = new
            # the newest map stays until the first of the new schedule (same calibration, still true
            # depth); none stays when no map can follow (the calibration does not apply)
            self._engine, self.engine_note = engine, (note if engine is None else None)
            if engine is None:
                self.results.clear()

        if self.acquisition is None:
            swap(schedule)
        elif not self.acquisition.request_schedule(schedule, swap, timeout_s):
            raise DeviceUnavailable("schedule: the acquisition reached no set boundary "
                                    f"within {timeout_s:.0f} s")

    @property
    def has_engine(self) -> bool:
        return self._engine is not None

    def _live_engine(self) -> Reconstructor | None:
        return self._engine

    def image_size(self) -> tuple[int, int] | None:
        """The camera's (width, height), once devices exist."""
        if self.devices is None:
            return None
        caps = self.devices.camera.capabilities
        return (caps.width, caps.height)

    def camera_bit_depths(self) -> tuple[int, ...] | None:
        """The bit depths the camera can deliver, once devices exist (None before)."""
        if self.devices is None:
            return None
        return tuple(int(b) for b in self.devices.camera.capabilities.bit_depths)

    # -- control ---------------------------------------------------------------------------
    def set_exposure(self, exposure_ms: float) -> float:
        """Request ``exposure_ms`` from the next whole set (checked at the API
        boundary and by the devices)."""
        self._acq().request(exposure_ms=float(exposure_ms))
        return float(exposure_ms)

    def set_led(self, led: str) -> str:
        if led not in LEDS:
            raise InvalidRequest(f"led: must be one of {LEDS}, got {led!r}")
        self._acq().request(led=led)
        return led

    def set_rolling(self, rolling: bool) -> None:
        if rolling and self.bracketing:
            raise Conflict("mode: rolling maps cannot fuse an exposure bracket; "
                           "PUT /api/mode {\"bracket\": false} first")
        self._acq().set_rolling(rolling)

    @property
    def bracketing(self) -> bool:
        """Whole sets alternate between the exposure and +2 stops, fused per pixel in pairs."""
        return self.acquisition is not None and self.acquisition.bracket

    def set_bracket(self, on: bool, *, auto: bool = False) -> None:
        """Exposure bracketing on or off (set mode only: a rolling map has no pair of sets).

        Raises:
            Conflict: ``on`` while in rolling mode.
        """
        acq = self._acq()
        if on and acq.rolling:
            raise Conflict("bracket: exposure bracketing fuses whole sets; "
                           "PUT /api/mode {\"rolling\": false} first")
        self.reconstruction.set_bracket(on)
        acq.set_bracket(on)
        self.bracket_auto = bool(on and auto)

    def bracket_note(self) -> str | None:
        """What bracketing does to the depth rate, for the status (None when off)."""
        acq = self.acquisition
        if acq is None or not acq.bracket:
            return None
        how = "switched on by the auto-exposure: the scene spans more than one exposure" \
            if self.bracket_auto else "on"
        return (f"exposure bracketing {how}; each depth map fuses a {acq.exposure_ms:g} ms and a "
                f"{acq.bracket_long_ms:g} ms set, so the depth rate halves")

    def set_acquiring(self, on: bool) -> None:
        self._acq().set_acquiring(on)

    def _acq(self) -> Acquisition:
        if self.acquisition is None:
            raise DeviceUnavailable("instrument not started")
        return self.acquisition

    # -- results ---------------------------------------------------------------------------
    def why_no_result(self) -> Conflict | DeviceUnavailable | None:
        """Why no result can come now: a state the client can change (409) or a fault (503);
        None: one is on its way."""
        if not self.has_engine:
            return Conflict(f"no depth result: {self.engine_note or 'no calibration is active'}")
        if self.acquisition is None or not self.acquisition.acquiring:
            return Conflict("no depth result: acquisition is stopped")
        if self.acquisition.fault:
            return DeviceUnavailable(f"no depth result: device fault ({self.acquisition.fault})")
        return None

    def next_capture(self, timeout_s: float = 10.0, *,
                     exposure_ms: float | None = None) -> CaptureSet:
        """The next whole fringe set grabbed after this call (optionally at one exposure)."""
        acq = self._acq()
        if not acq.acquiring:
            raise Conflict("acquisition is stopped: start it to capture")
        seq = acq.sets.seq
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            seq, fs = acq.sets.wait_newer(seq, left)
            if fs is None:
                break
            if (exposure_ms is None
                    or abs(fs.exposure_ms - exposure_ms) <= 1e-3 * exposure_ms + 1e-3):
                return CaptureSet(fs.stack(), self.schedule, float(fs.exposure_ms),
                                  fs.led or DEFAULT_LED, bit_depth=self.config.bit_depth,
                                  extra={"frame_indices": fs.frame_indices})
        raise DeviceUnavailable(f"no complete fringe set within {timeout_s:.0f} s")

    def auto_exposure(self, *, saturation_limit: float = DEFAULT_SATURATION_LIMIT,
                      max_exposure_ms: float = EXPOSURE_RANGE_MS[1]) -> AutoExposureResult:
        """Search exposures on real sets, then keep the chosen one."""
        acq = self._acq()
        before = acq.exposure_ms
        bit_depth = self.config.bit_depth
        top = full_scale(bit_depth)

        def measure(exposure_ms: float) -> tuple[float, float]:
            self.set_exposure(exposure_ms)
            timeout = 5.0 + 3 * self.schedule.n_frames * max(exposure_ms, 30.0) / 1000.0
            frames = self.next_capture(timeout, exposure_ms=exposure_ms).frames
            fs = 255 if frames.dtype.itemsize == 1 else top
            return set_statistics(frames, self.schedule, fs)

        was_bracketing, self.bracket_dim_share = self.bracketing, None
        if was_bracketing:  # the search grabs sets at its own exposures
            self.set_bracket(False)
        try:
            result = choose_exposure(measure, saturation_limit=saturation_limit,
                                     max_exposure_ms=max_exposure_ms)
        except Exception:
            self.set_exposure(before)
            if was_bracketing:
                self.set_bracket(True, auto=self.bracket_auto)
            raise
        self.set_exposure(result.exposure_ms)
        self.auto_bracket(result.exposure_ms, max_exposure_ms)
        return result

    def auto_bracket(self, exposure_ms: float, max_exposure_ms: float) -> float | None:
        """After the auto-exposure: bracketing on when the scene's range exceeds one exposure —
        more than :data:`BRACKET_DIM_SHARE` of its lit, unsaturated pixels invalid for low signal
        at ``exposure_ms`` while a longer exposure is possible — else off (in set mode only).

        Returns:
            The dim share measured on a set at ``exposure_ms`` (None: no engine, nothing judged).
        """
        engine, acq = self._engine, self._acq()
        if engine is None or acq.rolling:
            return None
        timeout = 5.0 + 3 * self.schedule.n_frames * max(exposure_ms, 30.0) / 1000.0
        capture = self.next_capture(timeout, exposure_ms=exposure_ms)
        frames = capture.frames
        full = 255.0 if frames.dtype == np.uint8 else float(full_scale(self.config.bit_depth))
        res = engine.run(frames, noise=self.reconstruction.live_noise(engine, full),
                         phase_error=self.reconstruction.noise.phase_error(engine.calibration.pattern))
        dim = np.isin(res.reason, (int(Reason.LOW_MODULATION), int(Reason.UNCERTAIN)))
        lit = res.texture > 0.02 * capture.max_code  # the scene, not the unlit background
        considered = lit & (res.reason != int(Reason.SATURATED))
        share = float(dim[considered].mean()) if considered.any() else 0.0
        longer = len(bracket_exposures(exposure_ms, max_exposure_ms=max_exposure_ms)) > 1
        self.set_bracket(share > BRACKET_DIM_SHARE and longer, auto=True)
        self.bracket_dim_share = share
        return share
