"""Abstract device interfaces in the manner of python-microscope.

Public methods validate arguments, keep the state machine, log, and map failures to
the :mod:`app.devices.errors` family; backends implement the small ``_do_*`` hooks.
A hook that raises :class:`DeviceDisconnected` puts the device in ``FAULT``; calling
``open()`` again is the recovery path.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.limits import (
    DEFAULT_EXPOSURE_MS,
    DEFAULT_LED,
    EXPOSURE_RANGE_MS,
    LEDS,
    check_exposure_ms,
    check_led,
)
from app.core.schedule import PatternSchedule
from app.devices.errors import DeviceDisconnected, DeviceError, DeviceStateError

__all__ = ["EXPOSURE_RANGE_MS", "LEDS"]  # re-exported: the devices' limits are the instrument's


class DeviceState(enum.StrEnum):
    CLOSED = "closed"
    OPEN = "open"
    RUNNING = "running"
    FAULT = "fault"


@dataclass(frozen=True)
class Frame:
    """One camera image and what is known about it.

    Attributes:
        data: (H, W) uint8 or uint16, as the sensor gives it.
        index: frame counter since ``start()`` (gaps mean dropped frames).
        timestamp: exposure mid-point, seconds (``time.monotonic`` clock or the recording's).
        pattern_index: position of the projected pattern in the schedule, -1 if unknown.
        exposure_ms, gain, led: settings in force for this frame.
        bit_depth: significant bits of ``data`` (e.g. 12 for Mono12 in uint16); the
            saturation code is ``2**bit_depth − 1``.
    """

    data: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
    index: int
    timestamp: float
    pattern_index: int = -1
    exposure_ms: float = math.nan
    gain: float = 1.0
    led: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    bit_depth: int = 8


@dataclass(frozen=True)
class CameraSettings:
    exposure_ms: float = DEFAULT_EXPOSURE_MS
    gain: float = 1.0
    bit_depth: int = 8


@dataclass(frozen=True)
class CameraCapabilities:
    width: int
    height: int
    bit_depths: tuple[int, ...] = (8,)
    exposure_range_ms: tuple[float, float] = EXPOSURE_RANGE_MS
    gain_range: tuple[float, float] = (1.0, 1.0)
    hardware_trigger: bool = False


class Device(ABC):
    """State, locking and logging common to every device kind."""

    kind = "device"

    def __init__(self, *, name: str | None = None) -> None:
        self.name = name or type(self).__name__
        self.log = logging.getLogger(f"fringescope.devices.{self.name}")
        self._lock = threading.RLock()
        self._state = DeviceState.CLOSED
        self.last_error: str = ""

    @property
    def state(self) -> DeviceState:
        return self._state

    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """Run a hook; a disconnect moves the device to FAULT with the reason kept."""
        try:
            return fn(*args, **kwargs)
        except DeviceDisconnected as exc:
            self._state = DeviceState.FAULT
            self.last_error = f"{self.name}: {exc}"
            self.log.warning("%s failed: %s", what, exc)
            raise
        except DeviceError as exc:
            self.last_error = f"{self.name}: {exc}"
            raise

    def _require(self, *states: DeviceState, action: str) -> None:
        if self._state not in states:
            raise DeviceStateError(f"{self.name}: cannot {action} while {self._state.value}")

    def open(self) -> None:
        """Connect to the device (also the way back from FAULT)."""
        with self._lock:
            if self._state in (DeviceState.OPEN, DeviceState.RUNNING):
                return
            if self._state is DeviceState.FAULT:
                try:
                    self._do_close()
                except Exception:  # a faulted link may fail to close; reopen anyway
                    self.log.debug("close of faulted device failed", exc_info=True)
            self._call("open", self._do_open)
            self._state = DeviceState.OPEN
            self.last_error = ""
            self.log.info("opened")

    def close(self) -> None:
        """Disconnect; safe to call in any state."""
        with self._lock:
            if self._state is DeviceState.CLOSED:
                return
            try:
                if self._state is DeviceState.RUNNING:
                    self._do_stop()
                self._do_close()
            except DeviceError as exc:
                self.log.warning("close: %s", exc)
            finally:
                self._state = DeviceState.CLOSED
                self.log.info("closed")

    def stop(self) -> None:
        """Leave RUNNING (a no-op in any other state); the device stays open."""
        with self._lock:
            if self._state is DeviceState.RUNNING:
                self._call("stop", self._do_stop)
                self._state = DeviceState.OPEN

    def __enter__(self) -> Device:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "state": self._state.value,
                "error": self.last_error}

    @abstractmethod
    def _do_open(self) -> None: ...

    @abstractmethod
    def _do_close(self) -> None: ...

    def _do_stop(self) -> None:  # noqa: B027 - optional hook
        pass


class Camera(Device):
    """A camera that delivers :class:`Frame` objects, one per projected pattern."""

    kind = "camera"

    def __init__(self, *, name: str | None = None) -> None:
        super().__init__(name=name)
        self._settings = CameraSettings()

    @property
    def settings(self) -> CameraSettings:
        return self._settings

    @property
    def capabilities(self) -> CameraCapabilities:
        return self._capabilities()

    def configure(
        self, *, exposure_ms: float | None = None, gain: float | None = None,
        bit_depth: int | None = None,
    ) -> CameraSettings:
        """Change settings (allowed while running; they apply from the next frame)."""
        caps = self.capabilities
        new = self._settings
        if exposure_ms is not None:
            lo, hi = caps.exposure_range_ms
            if not (math.isfinite(exposure_ms) and lo <= exposure_ms <= hi):
                raise ValueError(f"exposure_ms: must be within {lo}–{hi} ms, got {exposure_ms}")
            new = replace(new, exposure_ms=float(exposure_ms))
        if gain is not None:
            lo, hi = caps.gain_range
            if not (math.isfinite(gain) and lo <= gain <= hi):
                raise ValueError(f"gain: must be within {lo}–{hi}, got {gain}")
            new = replace(new, gain=float(gain))
        if bit_depth is not None:
            if bit_depth not in caps.bit_depths:
                raise ValueError(f"bit_depth: must be one of {caps.bit_depths}, got {bit_depth}")
            new = replace(new, bit_depth=int(bit_depth))
        with self._lock:
            if self._state is not DeviceState.CLOSED:
                self._call("configure", self._do_configure, new)
            self._settings = new
        self.log.debug("configured %s", new)
        return new

    def start(self) -> None:
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="start")
            if self._state is DeviceState.RUNNING:
                return
            self._call("configure", self._do_configure, self._settings)
            self._call("start", self._do_start)
            self._state = DeviceState.RUNNING

    def grab(self, timeout_s: float = 1.0) -> Frame:
        """Next frame; raises DeviceTimeout, DeviceDisconnected or DeviceStateError.

        Not under the device lock: a blocking grab must not stall ``configure``.
        """
        if self._state is not DeviceState.RUNNING:
            raise DeviceStateError(f"{self.name}: cannot grab while {self._state.value}")
        if not (timeout_s > 0):
            raise ValueError(f"timeout_s: must be positive, got {timeout_s}")
        frame: Frame = self._call("grab", self._do_grab, float(timeout_s))
        return frame

    @abstractmethod
    def _capabilities(self) -> CameraCapabilities: ...

    @abstractmethod
    def _do_configure(self, settings: CameraSettings) -> None: ...

    @abstractmethod
    def _do_start(self) -> None: ...

    @abstractmethod
    def _do_grab(self, timeout_s: float) -> Frame: ...


def significant_bits(data: npt.NDArray[np.uint8] | npt.NDArray[np.uint16], source_bits: int) -> int:
    """The full-scale rule of a camera frame: the bits its codes may fill.

    Args:
        data: the (H, W) mono frame, uint8 or uint16.
        source_bits: the bits the source fills in a 16-bit sample (12 for Mono12, 16 for
            Mono16 or a 16-bit OpenCV source, whose packing is unknown: full scale).

    Returns:
        8 for uint8 data, else ``source_bits``; the saturation code is ``2**bits − 1``.
    """
    if data.dtype == np.uint8:
        return 8
    if not 8 < source_bits <= 16:
        raise ValueError(f"source_bits: must be within 9–16 for uint16 data, got {source_bits}")
    return int(source_bits)


class CountingCamera(Camera):
    """A camera that learns the pattern index by trigger counting.

    After ``start()`` (or :meth:`sync`) frame ``k`` shows pattern ``k mod schedule_length``.
    """

    def __init__(self, *, schedule_length: int, name: str | None = None) -> None:
        super().__init__(name=name)
        if schedule_length < 1:
            raise ValueError(f"schedule_length: must be >= 1, got {schedule_length}")
        self.schedule_length = schedule_length
        self._count = 0
        self._sync_at = 0

    def sync(self) -> None:
        """Declare that the next frame shows pattern 0 (e.g. after the projector restarted)."""
        self._sync_at = self._count

    def _frame(self, data: npt.NDArray[np.uint8] | npt.NDArray[np.uint16], stamp: float, *,
               source_bits: int, meta: dict[str, Any] | None = None) -> Frame:
        """The grab tail: count the frame and stamp it with the settings in force."""
        index = self._count
        self._count += 1
        s = self._settings
        return Frame(data=data, index=index, timestamp=stamp,
                     pattern_index=(index - self._sync_at) % self.schedule_length,
                     exposure_ms=s.exposure_ms, gain=s.gain, meta=dict(meta or {}),
                     bit_depth=significant_bits(data, source_bits))


class LedMixin(Device):
    """The LED a device lights and its current: the projector's and the LED/trigger box's.

    A closed device only remembers the choice and applies it when opened.
    """

    def __init__(self, *, name: str | None = None) -> None:
        super().__init__(name=name)
        self.led: str = DEFAULT_LED
        self.led_current = 0.5  # fraction 0–1 of the backend's maximum current

    def set_led(self, led: str, *, current: float | None = None) -> None:
        """Select the LED (red/green/blue) and optionally its current (fraction 0–1)."""
        check_led(led)
        cur = self.led_current if current is None else float(current)
        if not (0.0 <= cur <= 1.0):
            raise ValueError(f"current: must be within 0–1, got {current}")
        with self._lock:
            if self._state is not DeviceState.CLOSED:
                self._call("set_led", self._do_set_led, led, cur)
            self.led, self.led_current = led, cur

    @abstractmethod
    def _do_set_led(self, led: str, current: float) -> None: ...


class Projector(LedMixin):
    """A pattern projector: a fringe schedule shown in sequence under one LED."""

    kind = "projector"

    def __init__(self, *, name: str | None = None) -> None:
        super().__init__(name=name)
        self.schedule: PatternSchedule | None = None
        self.exposure_ms = DEFAULT_EXPOSURE_MS

    def load_schedule(self, schedule: PatternSchedule, *, exposure_ms: float | None = None) -> None:
        """Upload the patterns of ``schedule`` (and the per-pattern exposure, ms)."""
        if not isinstance(schedule, PatternSchedule):
            raise ValueError("schedule: expected a PatternSchedule")
        exp = self.exposure_ms if exposure_ms is None else check_exposure_ms(exposure_ms)
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="load a schedule")
            self._call("load", self._do_load, schedule, exp)
            self.schedule, self.exposure_ms = schedule, exp

    def set_exposure(self, exposure_ms: float) -> None:
        """Change the per-pattern exposure, ms, keeping the uploaded patterns (a timing call only).

        Allowed while running (the sequence restarts at pattern 0 where the hardware needs
        a stop to change its timing). Before a schedule is loaded it is only remembered.
        """
        exp = check_exposure_ms(exposure_ms)  # the device-side check (the API checks once more)
        with self._lock:
            if self._state is not DeviceState.CLOSED and self.schedule is not None:
                self._call("timing", self._do_set_exposure, exp)
            self.exposure_ms = exp

    def start(self) -> None:
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="start")
            if self.schedule is None:
                raise DeviceStateError(f"{self.name}: load a schedule before start")
            if self._state is DeviceState.OPEN:
                self._call("start", self._do_start)
                self._state = DeviceState.RUNNING

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "led": self.led, "led_current": self.led_current}

    @abstractmethod
    def _do_load(self, schedule: PatternSchedule, exposure_ms: float) -> None: ...

    @abstractmethod
    def _do_set_exposure(self, exposure_ms: float) -> None:
        """Set the pattern timing for ``exposure_ms`` without uploading patterns again."""

    @abstractmethod
    def _do_start(self) -> None: ...


class Controller(LedMixin):
    """The LED/trigger box: LED channel and current, trigger arming, watchdog heartbeat."""

    kind = "controller"

    def __init__(self, *, name: str | None = None) -> None:
        super().__init__(name=name)
        self.armed = False
        self.frames_per_set = 16  # camera triggers per armed sequence: the schedule's frames

    def set_sequence_length(self, n_frames: int) -> None:
        """Camera triggers per armed sequence: the frames of one depth map (a schedule's
        ``n_frames``).

        Refused while armed (the firmware changes no timing while armed); a closed device
        only remembers it and sends it when opened.
        """
        if (isinstance(n_frames, bool) or int(n_frames) != n_frames
                or not 1 <= int(n_frames) <= 65535):
            raise ValueError(f"n_frames: need an integer within 1–65535, got {n_frames!r}")
        n = int(n_frames)
        with self._lock:
            if self.armed:
                raise DeviceStateError(
                    f"{self.name}: cannot change the sequence length while armed")
            if self._state is not DeviceState.CLOSED:
                self._call("sequence", self._do_set_sequence_length, n)
            self.frames_per_set = n

    def identify(self) -> str:
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="identify")
            return str(self._call("identify", self._do_identify))

    def arm(self) -> None:
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="arm")
            self._call("arm", self._do_arm, True)
            self.armed = True
            self._state = DeviceState.RUNNING

    def disarm(self) -> None:
        with self._lock:
            if self._state in (DeviceState.OPEN, DeviceState.RUNNING):
                self._call("disarm", self._do_arm, False)
            self.armed = False
            if self._state is DeviceState.RUNNING:
                self._state = DeviceState.OPEN

    def heartbeat(self) -> None:
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="send a heartbeat")
            self._call("heartbeat", self._do_heartbeat)

    def stop(self) -> None:
        """Leave RUNNING: for the LED/trigger box, disarm."""
        self.disarm()

    def _do_stop(self) -> None:
        self._do_arm(False)

    # optional hook (a box without a counter)
    def _do_set_sequence_length(self, n_frames: int) -> None:
        pass

    @abstractmethod
    def _do_identify(self) -> str: ...

    @abstractmethod
    def _do_arm(self, armed: bool) -> None: ...

    @abstractmethod
    def _do_heartbeat(self) -> None: ...
