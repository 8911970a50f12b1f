"""Fault injection for the simulated devices: dropped frames, timeouts, unplug/replug."""

from __future__ import annotations

import time

import numpy as np

from app.devices.errors import DeviceDisconnected, DeviceNotFound


class Link:
    """The cable of one simulated device: can be unplugged now, or every ``disconnect_every_s``.

    After an unplug the device is absent until ``reconnect_delay_s`` has passed (or
    :meth:`replug` is called): hooks raise DeviceDisconnected, ``open()`` DeviceNotFound.
    """

    def __init__(self, name: str, *, disconnect_every_s: float = 0.0,
                 reconnect_delay_s: float = 0.5) -> None:
        if disconnect_every_s < 0:
            raise ValueError(f"disconnect_every_s: must be >= 0, got {disconnect_every_s}")
        self.name = name
        self.every_s = float(disconnect_every_s)
        self.reconnect_delay_s = float(reconnect_delay_s)
        self._down_until = -np.inf  # while now < this, the device is unplugged
        self._down_manual = False
        self._next_unplug = np.inf

    def opened(self) -> None:
        """Open succeeded: arm the periodic unplug."""
        self._next_unplug = time.monotonic() + self.every_s if self.every_s > 0 else np.inf

    def unplug(self, *, for_s: float | None = None) -> None:
        """Pull the cable (until :meth:`replug` if ``for_s`` is None)."""
        if for_s is None:
            self._down_manual = True
        else:
            self._down_until = time.monotonic() + for_s

    def replug(self) -> None:
        self._down_manual = False
        self._down_until = -np.inf

    @property
    def present(self) -> bool:
        return not self._down_manual and time.monotonic() >= self._down_until

    def check(self) -> None:
        """Raise DeviceDisconnected if the link is (or just went) down."""
        now = time.monotonic()
        if now >= self._next_unplug:
            self._next_unplug = np.inf
            self.unplug(for_s=self.reconnect_delay_s)
        if not self.present:
            raise DeviceDisconnected(f"{self.name}: link lost (simulated unplug)")

    def check_open(self) -> None:
        if not self.present:
            raise DeviceNotFound(f"{self.name}: not connected (simulated unplug)")


class FrameFaults:
    """Per-frame random faults with their own seeded generator."""

    def __init__(self, *, drop_rate: float = 0.0, timeout_rate: float = 0.0,
                 seed: int | np.random.SeedSequence | None = None) -> None:
        for name, rate in (("drop_rate", drop_rate), ("timeout_rate", timeout_rate)):
            if not 0.0 <= rate < 1.0:
                raise ValueError(f"{name}: must be within [0, 1), got {rate}")
        self.drop_rate, self.timeout_rate = float(drop_rate), float(timeout_rate)
        self._rng = np.random.default_rng(seed)
        self.dropped = 0
        self.timeouts = 0

    def drop(self) -> bool:
        hit = self.drop_rate > 0 and self._rng.random() < self.drop_rate
        self.dropped += int(hit)
        return bool(hit)

    def timeout(self) -> bool:
        hit = self.timeout_rate > 0 and self._rng.random() < self.timeout_rate
        self.timeouts += int(hit)
        return bool(hit)
