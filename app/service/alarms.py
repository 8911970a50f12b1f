"""Alarms: faults the user must see and acknowledge (a recording that stopped on its own).

A warning in ``GET /api/status`` describes the present; an alarm records that something
happened and stays, across page reloads, until someone acknowledges it
(``POST /api/alarms/{id}/ack``). Thread-safe: raised from the recorder's threads, read
and acknowledged from request threads.
"""

from __future__ import annotations

import threading
from dataclasses import replace
from datetime import UTC, datetime

from app.core.errors import NotFound
from app.core.records import Alarm

__all__ = ["AlarmBoard"]


class AlarmBoard:
    """The alarms raised since start-up, newest last; at most ``keep`` are kept.

    Args:
        keep: alarms kept (acknowledged ones are dropped first when more are raised).
    """

    def __init__(self, keep: int = 100) -> None:
        if keep < 1:
            raise ValueError(f"keep: must be at least 1, got {keep}")
        self._keep = int(keep)
        self._lock = threading.Lock()
        self._alarms: list[Alarm] = []
        self._next_id = 1

    def raise_alarm(self, source: str, message: str) -> Alarm:
        """Record a new unacknowledged alarm from ``source`` (e.g. ``recorder``)."""
        at = datetime.now(UTC).isoformat(timespec="milliseconds")
        with self._lock:
            alarm = Alarm(id=self._next_id, source=source, message=message, raised_at=at)
            self._next_id += 1
            self._alarms.append(alarm)
            while len(self._alarms) > self._keep:
                acked = next((a for a in self._alarms if a.acknowledged_at is not None), None)
                self._alarms.remove(acked if acked is not None else self._alarms[0])
            return alarm

    def active(self) -> tuple[Alarm, ...]:
        """The alarms not yet acknowledged, oldest first."""
        with self._lock:
            return tuple(a for a in self._alarms if a.acknowledged_at is None)

    def all(self) -> tuple[Alarm, ...]:
        """Every kept alarm, acknowledged or not, oldest first."""
        with self._lock:
            return tuple(self._alarms)

    def acknowledge(self, alarm_id: int) -> Alarm:
        """Mark alarm ``alarm_id`` acknowledged (again: unchanged); NotFound if unknown."""
        at = datetime.now(UTC).isoformat(timespec="milliseconds")
        with self._lock:
            for i, alarm in enumerate(self._alarms):
                if alarm.id == alarm_id:
                    if alarm.acknowledged_at is None:
                        alarm = self._alarms[i] = replace(alarm, acknowledged_at=at)
                    return alarm
        raise NotFound(f"alarm_id: no alarm {alarm_id}")
