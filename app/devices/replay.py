"""A recorded session played back as a camera.

The recording is a folder of capture-set folders (sorted by name), or a single
capture-set folder. Sets are read lazily, one at a time, so a recording larger
than memory replays; a set that vanished or became unreadable during the replay
is a :class:`DeviceDisconnected` (like a camera unplug).

Pacing: ``pace=True`` reproduces the recorded timing — ``capture.json`` may carry
``"timestamps_s"`` (one per frame, seconds, increasing); without it frames are
spaced by the set's ``exposure_ms`` plus ``gap_ms``. ``pace=False`` delivers as
fast as ``grab`` is called. ``speed`` scales the replay rate.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.capture.captureset import CaptureSet, read_capture_set
from app.devices.base import Camera, CameraCapabilities, CameraSettings, Frame
from app.devices.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout


def find_capture_sets(root: str | Path) -> list[Path]:
    """Capture-set folders of a recording (``root`` itself if it is one), sorted by name."""
    folder = Path(root)
    if (folder / "capture.json").is_file():
        return [folder]
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if (p / "capture.json").is_file())


class ReplayCamera(Camera):
    """Frames of a recording at ``folder``, in capture-set order, with pattern indices.

    Args:
        pace: keep the recorded timing (see module doc) instead of delivering at once.
        loop: start over after the last set instead of timing out.
        speed: replay rate relative to the recording (2.0 = twice as fast).
        gap_ms: pause between frames added to ``exposure_ms`` when no timestamps were recorded.
    """

    def __init__(self, folder: str | Path, *, pace: bool = True, loop: bool = True,
                 speed: float = 1.0, gap_ms: float = 5.0, name: str | None = None) -> None:
        super().__init__(name=name or f"ReplayCamera({Path(folder).name})")
        if not speed > 0:
            raise ValueError(f"speed: must be positive, got {speed}")
        if gap_ms < 0:
            raise ValueError(f"gap_ms: must be >= 0, got {gap_ms}")
        self.folder, self.pace, self.loop = Path(folder), pace, loop
        self.speed, self.gap_ms = speed, gap_ms
        self._sets: list[Path] = []
        self._caps: CameraCapabilities | None = None
        self._current: CaptureSet | None = None
        self._times: npt.NDArray[np.float64] = np.zeros(0)
        self._set_pos = 0  # index into _sets of the set being played
        self._frame_pos = 0  # next frame within the current set
        self._last_t = 0.0  # recording time of the previous frame (continuous across sets)
        # (wall time, recording time) of the first frame
        self._anchor: tuple[float, float] | None = None
        self._count = 0

    # --- hooks --------------------------------------------------------------------------------
    def _do_open(self) -> None:
        sets = find_capture_sets(self.folder)
        if not sets:
            raise DeviceNotFound(f"{self.folder}: no capture sets (folders with capture.json)")
        first = self._read(sets[0])
        self._sets = sets
        self._caps = self._caps_of(first)
        self._rewind()

    def _do_close(self) -> None:
        self._current = None

    def _caps_of(self, cs: CaptureSet) -> CameraCapabilities:
        _, h, w = cs.frames.shape
        if cs.frames.dtype == np.uint8:
            depths: tuple[int, ...] = (8,)
        else:
            depths = (cs.bit_depth,) if cs.bit_depth else (12, 16)
        return CameraCapabilities(width=w, height=h, bit_depths=depths)

    def _capabilities(self) -> CameraCapabilities:
        if self._caps is None:
            sets = find_capture_sets(self.folder)
            if not sets:
                raise DeviceNotFound(f"{self.folder}: no capture sets (folders with capture.json)")
            self._caps = self._caps_of(self._read(sets[0]))
        return self._caps

    def _do_configure(self, settings: CameraSettings) -> None:
        pass  # recorded frames are what they are; settings only label frames

    def _do_start(self) -> None:
        self._anchor = None  # the first frame after start is due at once

    def _do_stop(self) -> None:
        pass

    def _do_grab(self, timeout_s: float) -> Frame:
        cs = self._ensure_set()
        t_rec = float(self._times[self._frame_pos])
        if self.pace:
            if self._anchor is None:
                self._anchor = (time.monotonic(), t_rec)
            due = self._anchor[0] + (t_rec - self._anchor[1]) / self.speed
            wait = due - time.monotonic()
            if wait > timeout_s:
                time.sleep(timeout_s)
                raise DeviceTimeout(
                    f"next recorded frame is {wait:.2f} s away (timeout {timeout_s:.2f} s)")
            if wait > 0:
                time.sleep(wait)
        i = self._frame_pos
        self._frame_pos += 1
        self._last_t = t_rec
        index, self._count = self._count, self._count + 1
        return Frame(data=cs.frames[i], index=index,
                     timestamp=time.monotonic() if self.pace else t_rec,
                     pattern_index=i, exposure_ms=cs.exposure_ms, led=cs.led,
                     meta={"set": self._sets[self._set_pos].name, "recorded_time_s": t_rec},
                     bit_depth=cs.bit_depth or (8 if cs.frames.dtype == np.uint8 else 16))

    # --- playback position ----------------------------------------------------------------------
    def _rewind(self) -> None:
        self._set_pos, self._frame_pos, self._current, self._last_t = 0, 0, None, 0.0

    def _read(self, path: Path) -> CaptureSet:
        try:
            return read_capture_set(path)
        except ValueError as exc:
            raise DeviceDisconnected(f"recording unreadable: {exc}") from None

    def _ensure_set(self) -> CaptureSet:
        """The set holding the next frame, loading the following set (or looping) as needed."""
        if self._current is not None and self._frame_pos >= len(self._times):
            self._current = None
            self._set_pos += 1
            self._frame_pos = 0
            if self._set_pos >= len(self._sets):
                if not self.loop:
                    self._set_pos = len(self._sets)
                    raise DeviceTimeout(f"{self.folder}: end of recording")
                self._set_pos = 0
        if self._set_pos >= len(self._sets):
            raise DeviceTimeout(f"{self.folder}: end of recording")
        if self._current is None:
            cs = self._read(self._sets[self._set_pos])
            caps = self._caps
            if caps is not None and cs.frames.shape[1:] != (caps.height, caps.width):
                raise DeviceDisconnected(
                    f"{self._sets[self._set_pos]}: frame size differs from the first set")
            self._current, self._times = cs, self._frame_times(cs)
        return self._current

    def _frame_times(self, cs: CaptureSet) -> npt.NDArray[np.float64]:
        """Recording times of the set's frames, continuing after the previous frame."""
        n = cs.frames.shape[0]
        step = (cs.exposure_ms + self.gap_ms) / 1000.0
        stamps: Any = cs.extra.get("timestamps_s")
        numbers = isinstance(stamps, list) and all(isinstance(t, (int, float)) for t in stamps)
        if numbers and len(stamps) == n:
            t = np.asarray(stamps, np.float64)
            if np.all(np.diff(t) > 0):
                # relative stamps or a loop: continue the clock
                if self._count and t[0] <= self._last_t:
                    if n > 1:
                        t = t - t[0] + self._last_t + float(np.median(np.diff(t)))
                    else:
                        t = t + self._last_t + step
                return t
        start = self._last_t + step if self._count else 0.0
        return start + step * np.arange(n, dtype=np.float64)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "folder": str(self.folder), "sets": len(self._sets)}
