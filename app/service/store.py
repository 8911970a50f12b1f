"""Thread hand-offs: a newest-wins queue, a "latest value" slot streams can wait on, rates."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np

T = TypeVar("T")
log = logging.getLogger("fringescope.service.store")


class NewestQueue(Generic[T]):
    """A bounded queue where ``put`` never blocks: when full, the oldest item is dropped.

    ``dropped`` counts items that were replaced before anyone took them.
    """

    def __init__(self, maxsize: int = 1) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize: must be >= 1, got {maxsize}")
        self._items: deque[T] = deque()
        self._maxsize = maxsize
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, item: T) -> None:
        with self._cond:
            while len(self._items) >= self._maxsize:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()

    def get(self, timeout_s: float) -> T | None:
        """The oldest queued item, or ``None`` after ``timeout_s`` seconds."""
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._items), timeout=timeout_s):
                return None
            return self._items.popleft()

    def clear(self) -> None:
        with self._cond:
            self._items.clear()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class LatestSlot(Generic[T]):
    """The most recent value with a sequence number; readers wait for a newer one.

    ``publish`` numbers values 1, 2, …; ``wait_newer(after_seq)`` returns the first value
    with a higher number (or ``None`` on timeout or after ``close()``).
    ``subscribe(callback)`` calls ``callback(seq, value)`` on every publish, on the
    publisher's thread after the value is visible: callbacks must only hand over (e.g. to a
    :class:`NewestQueue`), never block; an exception in one is logged and ignored.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._value: T | None = None
        self._seq = 0
        self._closed = False
        self._subscribers: list[Callable[[int, T], None]] = []

    @property
    def seq(self) -> int:
        return self._seq

    @property
    def closed(self) -> bool:
        return self._closed

    def publish(self, value: T) -> int:
        with self._cond:
            self._seq += 1
            seq = self._seq
            self._value = value
            self._cond.notify_all()
            subscribers = list(self._subscribers)
        for callback in subscribers:
            try:
                callback(seq, value)
            except Exception:
                log.exception("result subscriber %r failed", callback)
        return seq

    def subscribe(self, callback: Callable[[int, T], None]) -> Callable[[], None]:
        """Call ``callback(seq, value)`` on every publish; returns the unsubscribe function."""
        with self._cond:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._cond:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe

    def latest(self) -> tuple[int, T | None]:
        with self._cond:
            return self._seq, self._value

    def wait_newer(self, after_seq: int, timeout_s: float) -> tuple[int, T | None]:
        with self._cond:
            self._cond.wait_for(lambda: self._seq > after_seq or self._closed, timeout=timeout_s)
            if self._seq > after_seq:
                return self._seq, self._value
            return self._seq, None

    def clear(self) -> None:
        with self._cond:
            self._value = None

    def close(self) -> None:
        """Wake every waiter for good (shutdown)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class RateMeter:
    """Events per second over a sliding window of ``window_s`` seconds (monotonic clock)."""

    def __init__(self, window_s: float = 3.0) -> None:
        self.window_s = window_s
        self._times: deque[float] = deque()
        self._lock = threading.Lock()

    def tick(self, t: float | None = None) -> None:
        now = time.monotonic() if t is None else t
        with self._lock:
            self._times.append(now)
            self._trim(now)

    def _trim(self, now: float) -> None:
        while self._times and now - self._times[0] > self.window_s:
            self._times.popleft()

    def rate(self) -> float:
        """Events per second; 0 until two events fall in the window."""
        now = time.monotonic()
        with self._lock:
            self._trim(now)
            if len(self._times) < 2:
                return 0.0
            span = self._times[-1] - self._times[0]
            # The window may extend past the last event: a stalled stream should decay.
            span = max(span, now - self._times[0] - span / (len(self._times) - 1))
            return (len(self._times) - 1) / span if span > 0 else 0.0


class RecentValues:
    """The last ``n`` values of a figure, for medians (e.g. latency, ms)."""

    def __init__(self, n: int = 50) -> None:
        self._values: deque[float] = deque(maxlen=n)
        self._lock = threading.Lock()

    def add(self, value: float) -> None:
        with self._lock:
            self._values.append(float(value))

    def median(self) -> float | None:
        with self._lock:
            return float(np.median(self._values)) if self._values else None

    def values(self) -> list[float]:
        with self._lock:
            return list(self._values)
