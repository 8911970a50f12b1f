"""The acquisition thread: grab frames, group them into sets, survive device faults.

Settings changes (exposure, LED) are applied between sets, so every reconstructed set
was taken with one setting. A device that times out or disconnects puts the thread in
a fault state (visible in status); the devices are re-opened with back-off until they
answer again. The thread never dies of a device error.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime

from app.core.limits import EXPOSURE_RANGE_MS
from app.core.schedule import PatternSchedule
from app.devices.base import Frame
from app.devices.errors import DeviceError, DeviceTimeout
from app.service.devices import (
    DeviceBundle,
    apply_settings,
    close_devices,
    start_devices,
    stop_devices,
)
from app.service.framesets import FrameSet, GroupWindow, SetAssembler, depth_group_of
from app.service.store import LatestSlot, NewestQueue, RateMeter, RecentValues

log = logging.getLogger("fringescope.service.acquisition")

BACKOFF_START_S = 0.2
BACKOFF_MAX_S = 3.0
HEARTBEAT_S = 0.5
TIMEOUTS_BEFORE_RESTART = 3


class Acquisition:
    """Owns the grab loop. Whole sets go to ``sets`` (latest) and, in set mode, ``queue``;
    in rolling mode the queue gets a set after every completed frequency group."""

    def __init__(
        self,
        devices: DeviceBundle,
        schedule: PatternSchedule,
        queue: NewestQueue[FrameSet],
        *,
        exposure_ms: float,
        led: str,
        bit_depth: int,
        rolling: bool = False,
        on_frame: Callable[[Frame], None] | None = None,
    ) -> None:
        self.devices = devices
        self.schedule = schedule
        self.queue = queue
        self.sets: LatestSlot[FrameSet] = LatestSlot()
        self.bit_depth = bit_depth
        self.exposure_ms = float(exposure_ms)
        self.led = led
        self.rolling = rolling
        # exposure bracketing: whole sets alternate between exposure_ms and bracket_long_ms
        self.bracket = False
        self.bracket_stops = 2.0
        self.on_frame = on_frame
        self.assembler = SetAssembler(schedule.n_frames, schedule.steps)
        self.window = GroupWindow(len(schedule.frequencies), schedule.steps,
                                  depth_group=depth_group_of(schedule.frequencies))
        self.camera_rate = RateMeter()
        self.frames_received = 0
        self.frames_dropped = 0
        # since the last set that reached the reconstruction queue: a camera that drops frames
        # often enough completes no set (each needs F consecutive frames) — status says so
        self.frames_since_set = 0
        self.dropped_since_set = 0
        self.faults = 0
        self.fault: str | None = None
        self.last_error: str | None = None
        self.last_error_s: float | None = None  # time.monotonic() of last_error
        self.last_error_at: str | None = None  # the same instant, ISO 8601 UTC
        self.last_frame_s: float | None = None  # time.monotonic() of the newest frame
        # timestamp intervals of consecutive frames, s: the camera's frame period as it runs
        self._intervals = RecentValues(64)
        self._last_timestamp = 0.0
        self._last_index: int | None = None
        self._pending: dict[str, object] = {}
        self._pending_schedule: tuple[PatternSchedule, Callable[[PatternSchedule], None],
                                      threading.Event] | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._want_running = threading.Event()
        self._started = False
        self._thread = threading.Thread(target=self._run, name="fringescope-acquisition",
                                        daemon=True)

    # -- control (any thread) ------------------------------------------------------
    def start_thread(self, *, acquire: bool = True) -> None:
        if acquire:
            self._want_running.set()
        self._thread.start()

    def shutdown(self, timeout_s: float = 10.0) -> None:
        """Stop the loop, stop and close the devices, join the thread."""
        self._stop.set()
        self._want_running.clear()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        close_devices(self.devices)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def acquiring(self) -> bool:
        return self._want_running.is_set()

    def set_acquiring(self, on: bool) -> None:
        if on:
            self._want_running.set()
        else:
            self._want_running.clear()

    def request(self, *, exposure_ms: float | None = None, led: str | None = None) -> None:
        """Ask for new settings; applied before the next whole set."""
        with self._lock:
            if exposure_ms is not None:
                self.exposure_ms = float(exposure_ms)
                self._pending["exposure_ms"] = float(exposure_ms)
            if led is not None:
                self.led = led
                self._pending["led"] = led

    def request_schedule(self, schedule: PatternSchedule,
                         on_swap: Callable[[PatternSchedule], None],
                         timeout_s: float = 10.0) -> bool:
        """Switch to ``schedule`` at the next set boundary and wait for it (True: switched).

        The loop stops the devices, swaps the schedule and the set assembly, calls
        ``on_swap(schedule)`` (nothing of the old schedule is produced after it), and starts
        the devices again, which loads the new patterns into the projector and the sequence
        length into the controller. Without a running loop the swap happens here.
        """
        done = threading.Event()
        with self._lock:
            self._pending_schedule = (schedule, on_swap, done)
        if not self._thread.is_alive():
            self._apply_schedule()
        return done.wait(timeout_s)

    def _apply_schedule(self) -> None:
        with self._lock:
            pending, self._pending_schedule = self._pending_schedule, None
        if pending is None:
            return
        schedule, on_swap, done = pending
        try:
            if self._started:
                stop_devices(self.devices)
                self._started = False  # the loop starts them again with the new patterns
            self.schedule = schedule
            self.assembler = SetAssembler(schedule.n_frames, schedule.steps)
            self.window = GroupWindow(len(schedule.frequencies), schedule.steps,
                                  depth_group=depth_group_of(schedule.frequencies))
            self.queue.clear()
            on_swap(schedule)
        finally:
            done.set()

    def set_rolling(self, rolling: bool) -> None:
        with self._lock:
            self.rolling = bool(rolling)
        self.window.clear()

    @property
    def bracket_long_ms(self) -> float:
        """The bracket's second exposure: ``bracket_stops`` stops over :attr:`exposure_ms`
        (capped at the longest exposure)."""
        long_ms = float(self.exposure_ms * 2.0**self.bracket_stops)
        return min(long_ms, float(EXPOSURE_RANGE_MS[1]))

    def set_bracket(self, on: bool) -> None:
        """Alternate whole sets between :attr:`exposure_ms` and :attr:`bracket_long_ms` (from the
        next set); off: back to :attr:`exposure_ms` alone."""
        with self._lock:
            self.bracket = bool(on)
            self._pending["exposure_ms"] = self.exposure_ms

    # -- the loop ----------------------------------------------------------------------
    def _run(self) -> None:
        backoff = BACKOFF_START_S
        timeouts = 0
        last_beat = 0.0
        while not self._stop.is_set():
            if self._pending_schedule is not None and self.assembler.in_progress == 0:
                self._apply_schedule()
            if not self._want_running.is_set():
                if self._started:
                    stop_devices(self.devices)
                    self._started = False
                    self._reset_sets()
                self._stop.wait(0.05)
                continue
            if not self._started:
                try:
                    self._start_devices()
                    backoff = BACKOFF_START_S
                except Exception as exc:  # any failure: report, back off, retry
                    self._record_fault(exc)
                    close_devices(self.devices)
                    self._stop.wait(backoff)
                    backoff = min(2 * backoff, BACKOFF_MAX_S)
                    continue
            try:
                now = time.monotonic()
                if self.devices.controller is not None and now - last_beat > HEARTBEAT_S:
                    self.devices.controller.heartbeat()
                    last_beat = now
                if self.assembler.in_progress == 0:
                    self._apply_pending()
                frame = self.devices.camera.grab(timeout_s=self._grab_timeout_s())
            except DeviceTimeout as exc:
                self._reset_sets()
                self._record_fault(exc)
                timeouts += 1
                if timeouts >= TIMEOUTS_BEFORE_RESTART:  # a stuck link: restart it
                    timeouts = 0
                    close_devices(self.devices)
                    self._started = False
                continue
            except Exception as exc:  # disconnects and anything unexpected
                if not isinstance(exc, DeviceError):
                    log.exception("acquisition error")
                self._reset_sets()
                self._record_fault(exc)
                close_devices(self.devices)
                self._started = False
                self._stop.wait(backoff)
                backoff = min(2 * backoff, BACKOFF_MAX_S)
                continue
            timeouts = 0
            backoff = BACKOFF_START_S
            self.fault = None
            self._on_frame(frame, time.monotonic())

    def _start_devices(self) -> None:
        with self._lock:
            exposure_ms, led = self.exposure_ms, self.led
            self._pending.clear()
        start_devices(self.devices, self.schedule, exposure_ms=exposure_ms, led=led,
                      bit_depth=self.bit_depth)
        self._started = True
        self._last_index = None
        self._reset_sets()

    def _apply_pending(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
        if pending:
            apply_settings(
                self.devices,
                exposure_ms=pending.get("exposure_ms"),  # type: ignore[arg-type]
                led=pending.get("led"),  # type: ignore[arg-type]
            )

    def _grab_timeout_s(self) -> float:
        return max(1.0, 4.0 * self.exposure_ms / 1000.0)

    def _reset_sets(self) -> None:
        self.assembler.abort()
        self.window.clear()

    def _record_fault(self, exc: BaseException) -> None:
        msg = str(exc) or type(exc).__name__
        if self.fault != msg:
            log.warning("device fault: %s", msg)
        self.fault = msg
        self.last_error = msg
        self.last_error_s = time.monotonic()
        self.last_error_at = datetime.now(UTC).isoformat(timespec="milliseconds")
        self.faults += 1

    @property
    def frame_period_s(self) -> float:
        """The camera's frame period, s: the median timestamp interval of consecutive frames
        (before any, the exposure). Intervals across a gap are not counted, so a
        stall does not stretch it."""
        median = self._intervals.median()
        return median if median is not None else max(self.exposure_ms, 1.0) / 1000.0

    def _on_frame(self, frame: Frame, received_s: float) -> None:
        self.frames_received += 1
        self.frames_since_set += 1
        if self._last_index is not None and frame.index > self._last_index + 1:
            self.frames_dropped += frame.index - self._last_index - 1
            self.dropped_since_set += frame.index - self._last_index - 1
        elif self._last_index is not None and frame.index == self._last_index + 1 \
                and 0.0 < frame.timestamp - self._last_timestamp < 10.0:
            # the camera's own clock: arrivals bunch when this thread is starved of CPU
            self._intervals.add(frame.timestamp - self._last_timestamp)
        self._last_index = frame.index
        self._last_timestamp = frame.timestamp
        self.last_frame_s = received_s
        self.camera_rate.tick(received_s)
        if self.on_frame is not None:
            self.on_frame(frame)
        whole = self.assembler.feed(frame, received_s)
        if whole is not None:
            self.sets.publish(whole)
            if self.bracket and not self.rolling:
                self._next_bracket_exposure(whole.exposure_ms)
        if self.rolling:
            rolled = self.window.feed(frame, received_s)
            if rolled is not None:
                self._queue_set(rolled)
        elif whole is not None:
            self._queue_set(whole)

    def _next_bracket_exposure(self, last_ms: float) -> None:
        """After a whole set at ``last_ms``: the next one at the bracket's other exposure."""
        with self._lock:
            if not self.bracket:  # switched off since the caller looked: keep set_bracket's reset
                return
            base = self.exposure_ms
            short = abs(last_ms - base) <= 1e-3 * base + 1e-3
            self._pending["exposure_ms"] = self.bracket_long_ms if short else base

    def _queue_set(self, frame_set: FrameSet) -> None:
        self.frames_since_set = self.dropped_since_set = 0
        self.queue.put(frame_set)
