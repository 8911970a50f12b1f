"""A camera through OpenCV ``VideoCapture``: UVC cameras, capture cards, streams, video files.

A reader thread pulls frames into a small queue so ``grab`` can time out. Frames are
converted to mono (8-bit, or 16-bit when the source gives 16-bit and ``bit_depth``
asks for 12/16). The pattern index comes from trigger counting: after ``start()``
(or :meth:`sync`) frame ``k`` shows pattern ``k mod schedule_length``.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from app.core.limits import EXPOSURE_RANGE_MS
from app.devices.base import CameraCapabilities, CameraSettings, CountingCamera, Frame
from app.devices.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout

FILE_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg")


def to_mono(image: npt.NDArray[Any],
            bit_depth: int = 8) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
    """(H, W) mono of a (H, W) / (H, W, 3|4) BGR(A) image; uint8, or uint16 if the source is
    and ``bit_depth`` > 8."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ValueError(f"image: expected (H, W) or (H, W, C), got {image.shape}")
    if img.dtype == np.uint16:
        return img if bit_depth > 8 else (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


class OpenCVCamera(CountingCamera):
    """OpenCV capture of ``source``: an int index, a device path, a URL or a video file.

    Args:
        schedule_length: patterns per set, for ``Frame.pattern_index``.
        loop: restart a video file at its end (default for files) instead of timing out.
        fps: pace a video file to this rate (None: the file's own rate; 0: as fast as possible).
        disconnect_after: consecutive failed reads of a live source taken as an unplug.
    """

    def __init__(self, source: int | str, *, schedule_length: int = 16, loop: bool = True,
                 fps: float | None = None, disconnect_after: int = 30, queue_size: int = 4,
                 name: str | None = None) -> None:
        super().__init__(schedule_length=schedule_length, name=name or f"OpenCVCamera({source})")
        if isinstance(source, str) and source.strip().isdigit():
            source = int(source)
        self.source = source
        self.is_file = isinstance(source, str) and source.lower().endswith(FILE_SUFFIXES)
        self.loop, self.fps = loop, fps
        self.disconnect_after, self.queue_size = disconnect_after, queue_size
        self._cap: cv2.VideoCapture | None = None
        self._size = (0, 0)
        self._queue: queue.Queue[tuple[npt.NDArray[Any], float] | BaseException] = queue.Queue(
            queue_size)
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None

    # --- hooks ---------------------------------------------------------------------------
    def _do_open(self) -> None:
        cap = cv2.VideoCapture(self.source)
        if not cap.isOpened():
            cap.release()
            raise DeviceNotFound(f"{self.source}: OpenCV cannot open it")
        ok, first = cap.read()
        if not ok or first is None:
            cap.release()
            raise DeviceNotFound(f"{self.source}: opened but delivers no frames")
        self._size = (first.shape[1], first.shape[0])
        if self.is_file:
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._cap = cap

    def _do_close(self) -> None:
        self._stop_reader()
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _capabilities(self) -> CameraCapabilities:
        if self._size == (0, 0):  # not opened yet: ask the source once
            self._do_open()
            self._do_close()
        return CameraCapabilities(width=self._size[0], height=self._size[1], bit_depths=(8, 12, 16),
                                  exposure_range_ms=EXPOSURE_RANGE_MS, gain_range=(1.0, 1.0))

    def _do_configure(self, settings: CameraSettings) -> None:
        cap = self._cap
        if cap is None or self.is_file or (isinstance(self.source, str) and "://" in self.source):
            return  # files and streams have no exposure control
        # exposure units are backend specific: V4L2 counts 100 µs, DirectShow/MSMF take
        # log2(seconds)
        if cap.getBackendName() == "V4L2":
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # 1 = manual in V4L2's menu
            cap.set(cv2.CAP_PROP_EXPOSURE, settings.exposure_ms * 10.0)
        else:
            cap.set(cv2.CAP_PROP_EXPOSURE, float(np.log2(settings.exposure_ms / 1000.0)))

    def _do_start(self) -> None:
        if self._cap is None:
            raise DeviceDisconnected("capture is not open")
        self.sync()
        self._stop.clear()
        self._queue = queue.Queue(self.queue_size)
        self._reader = threading.Thread(target=self._read_loop, args=(self._cap, self._queue),
                                        name=f"{self.name}-reader", daemon=True)
        self._reader.start()

    def _do_stop(self) -> None:
        self._stop_reader()

    def _do_grab(self, timeout_s: float) -> Frame:
        try:
            item = self._queue.get(timeout=timeout_s)
        except queue.Empty:
            raise DeviceTimeout(f"{self.source}: no frame within {timeout_s:.2f} s") from None
        if isinstance(item, BaseException):
            raise item
        image, stamp = item
        # OpenCV does not say how a 16-bit source packs its codes: full scale
        return self._frame(to_mono(image, self._settings.bit_depth), stamp, source_bits=16)

    # --- reader thread -----------------------------------------------------------------------
    def _stop_reader(self) -> None:
        self._stop.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        self._reader = None

    def _read_loop(self, cap: cv2.VideoCapture, out: queue.Queue[Any]) -> None:
        if self.fps is not None:
            rate = self.fps
        else:
            rate = cap.get(cv2.CAP_PROP_FPS) if self.is_file else 0.0
        period_s = 1.0 / rate if rate and rate > 0 else 0.0
        due, failures = time.monotonic(), 0
        while not self._stop.is_set():
            ok, image = cap.read()
            if not ok or image is None:
                rewound = self.is_file and self.loop and cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                if rewound and failures < 2:
                    failures += 1
                    continue
                failures += 1
                if self.is_file or failures >= self.disconnect_after:
                    end = (DeviceTimeout(f"{self.source}: end of video") if self.is_file
                           else DeviceDisconnected(f"{self.source}: no more frames"))
                    self._put(out, end)
                    return
                time.sleep(0.01)
                continue
            failures = 0
            if period_s:
                due += period_s
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            self._put(out, (image, time.monotonic()))

    def _put(self, out: queue.Queue[Any], item: Any) -> None:
        """Blocking for files (no frame skipped); drop the oldest for live sources (no lag)."""
        while not self._stop.is_set():
            try:
                out.put(item, timeout=0.05)
                return
            except queue.Full:
                if not self.is_file:
                    with contextlib.suppress(queue.Empty):
                        out.get_nowait()
