"""The tracker's poses: the newest TRANSFORM received per device (a tracked scope's pose).

The OpenIGTLink server writes them, the recorder stores them with each recorded set. Built
once by ``create_app`` and handed to both in their constructors, it keeps the server and
the recorder from needing each other.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass


@dataclass(frozen=True)
class ReceivedTransform:
    """A TRANSFORM message received: 4×4 matrix (mm), sender's timestamp (s since 1970)."""

    device_name: str
    matrix: list[list[float]]
    timestamp_s: float
    received_s: float  # time.time() on arrival

    def as_dict(self) -> dict[str, str | float | list[list[float]]]:
        return {"device_name": self.device_name, "matrix": self.matrix,
                "timestamp_s": self.timestamp_s, "received_s": self.received_s}


class TrackerPoses:
    """The newest :class:`ReceivedTransform` per device name; any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._newest: dict[str, ReceivedTransform] = {}

    def put(self, transform: ReceivedTransform) -> None:
        """Keep ``transform`` as its device's newest."""
        with self._lock:
            self._newest[transform.device_name] = transform

    def latest(self) -> dict[str, dict[str, str | float | list[list[float]]]]:
        """Device name → its newest transform as JSON (``{}``: none received)."""
        with self._lock:
            return {name: t.as_dict() for name, t in self._newest.items()}
