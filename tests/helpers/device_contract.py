"""The device contract: one suite every backend (simulator and real) must pass.

A backend's test module subclasses a mixin and provides a ``device`` fixture that
yields an UNOPENED device (and cleans up after). Backends that can be unplugged in
tests set ``supports_disconnect = True`` and implement ``disconnect(device)`` and
``reconnect(device)`` (e.g. close the pty, stop the fake TCP server, then bring it back).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from app.core.schedule import PatternSchedule, schedule_by_name
from app.devices import (
    Camera,
    Controller,
    DeviceDisconnected,
    DeviceError,
    DeviceState,
    DeviceStateError,
    DeviceTimeout,
    Projector,
)


class _Common:
    supports_disconnect = False
    recover_within_s = 2.0

    def disconnect(self, device):  # pragma: no cover - overridden where supported
        raise NotImplementedError

    def reconnect(self, device):  # pragma: no cover - overridden where supported
        raise NotImplementedError

    def exercise(self, device) -> None:
        """One call that talks to the device (so a vanished link is noticed)."""
        raise NotImplementedError

    def test_open_close_idempotent(self, device):
        assert device.state is DeviceState.CLOSED
        device.open()
        device.open()
        assert device.state is DeviceState.OPEN
        device.close()
        device.close()
        assert device.state is DeviceState.CLOSED

    def test_context_manager_closes(self, device):
        with device:
            assert device.state is DeviceState.OPEN
        assert device.state is DeviceState.CLOSED

    def test_describe(self, device):
        d = device.describe()
        assert {"name", "kind", "state", "error"} <= d.keys()
        assert d["state"] == "closed"

    def test_disconnect_faults_then_recovers(self, device):
        if not self.supports_disconnect:
            pytest.skip("backend cannot be unplugged in tests")
        device.open()
        self._start(device)
        self.disconnect(device)
        with pytest.raises(DeviceError):
            # the first call after the unplug may still succeed from buffers; a few must not
            for _ in range(50):
                self.exercise(device)
                time.sleep(0.02)
        assert device.state is DeviceState.FAULT
        assert device.last_error
        self.reconnect(device)
        deadline = time.monotonic() + self.recover_within_s
        while True:
            try:
                device.open()
                self._start(device)
                self.exercise(device)
                break
            except DeviceError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        assert device.state in (DeviceState.OPEN, DeviceState.RUNNING)
        device.close()

    def _start(self, device) -> None:
        pass


class CameraContract(_Common):
    """Every Camera backend: configure, start, grab frames with metadata, stop."""

    def exercise(self, device: Camera) -> None:
        device.grab(timeout_s=0.5)

    def _start(self, device: Camera) -> None:
        device.start()

    def test_is_camera(self, device):
        assert isinstance(device, Camera)

    def test_grab_before_start_is_a_state_error(self, device):
        device.open()
        with pytest.raises(DeviceStateError):
            device.grab(timeout_s=0.1)
        device.close()

    def test_grab_frames(self, device: Camera):
        caps = device.capabilities
        device.open()
        device.start()
        frames = [device.grab(timeout_s=5.0) for _ in range(3)]
        device.stop()
        device.close()
        for f in frames:
            assert f.data.ndim == 2
            assert f.data.dtype in (np.uint8, np.uint16)
            assert f.data.shape == (caps.height, caps.width)
        idx = [f.index for f in frames]
        assert idx == sorted(idx) and len(set(idx)) == 3
        ts = [f.timestamp for f in frames]
        assert ts == sorted(ts)

    def test_configure_validates(self, device: Camera):
        lo, hi = device.capabilities.exposure_range_ms
        with pytest.raises(ValueError, match="exposure_ms"):
            device.configure(exposure_ms=hi * 10)
        with pytest.raises(ValueError, match="exposure_ms"):
            device.configure(exposure_ms=float("nan"))
        with pytest.raises(ValueError, match="bit_depth"):
            device.configure(bit_depth=7)
        s = device.configure(exposure_ms=lo + (hi - lo) / 4)
        assert s.exposure_ms == pytest.approx(lo + (hi - lo) / 4)

    def test_grab_timeout_validated(self, device: Camera):
        device.open()
        device.start()
        with pytest.raises(ValueError, match="timeout_s"):
            device.grab(timeout_s=0)
        device.close()

    def test_stop_then_restart(self, device: Camera):
        device.open()
        device.start()
        device.grab(timeout_s=5.0)
        device.stop()
        assert device.state is DeviceState.OPEN
        device.start()
        device.grab(timeout_s=5.0)
        device.close()


class ProjectorContract(_Common):
    """Every Projector backend: load a schedule, choose LED, start/stop."""

    schedule = PatternSchedule()

    def exercise(self, device: Projector) -> None:
        device.set_led("green", current=0.4)

    def _start(self, device: Projector) -> None:
        device.load_schedule(self.schedule, exposure_ms=20.0)
        device.start()

    def test_is_projector(self, device):
        assert isinstance(device, Projector)

    def test_start_needs_schedule(self, device: Projector):
        device.open()
        with pytest.raises(DeviceStateError):
            device.start()
        device.close()

    def test_load_led_start_stop(self, device: Projector):
        device.open()
        device.load_schedule(self.schedule, exposure_ms=20.0)
        device.set_led("red", current=0.3)
        assert device.led == "red" and device.led_current == pytest.approx(0.3)
        device.start()
        assert device.state is DeviceState.RUNNING
        device.stop()
        assert device.state is DeviceState.OPEN
        device.close()

    def test_bad_led_and_current(self, device: Projector):
        with pytest.raises(ValueError, match="led"):
            device.set_led("purple")
        with pytest.raises(ValueError, match="current"):
            device.set_led("green", current=1.5)

    def test_schedule_switch(self, device: Projector):
        """A running projector takes another schedule: its patterns replace the old ones."""
        reduced = schedule_by_name("geometric-9")
        device.open()
        device.load_schedule(self.schedule, exposure_ms=20.0)
        device.start()
        device.load_schedule(reduced, exposure_ms=20.0)
        assert device.schedule == reduced and device.state is DeviceState.RUNNING
        self.check_loaded(device, reduced)
        device.stop()
        device.load_schedule(self.schedule, exposure_ms=20.0)
        self.check_loaded(device, self.schedule)
        device.close()

    def check_loaded(self, device: Projector, schedule: PatternSchedule) -> None:
        """Backends that can show what they hold check it here (the emulator's patterns, the
        twin's)."""


class ControllerContract(_Common):
    """Every Controller backend: identify, LED, arm/disarm, heartbeat."""

    def exercise(self, device: Controller) -> None:
        device.heartbeat()

    def _start(self, device: Controller) -> None:
        device.arm()

    def test_is_controller(self, device):
        assert isinstance(device, Controller)

    def test_identify(self, device: Controller):
        device.open()
        ident = device.identify()
        assert isinstance(ident, str) and ident
        device.close()

    def test_arm_disarm_heartbeat(self, device: Controller):
        device.open()
        device.set_led("blue", current=0.25)
        device.arm()
        assert device.armed and device.state is DeviceState.RUNNING
        device.heartbeat()
        device.disarm()
        assert not device.armed and device.state is DeviceState.OPEN
        device.close()

    def test_stop_disarms(self, device: Controller):
        """``stop`` leaves RUNNING as for every device: for the box that is a disarm."""
        device.open()
        device.arm()
        device.stop()
        assert not device.armed and device.state is DeviceState.OPEN
        device.stop()  # not running: nothing to do
        assert device.state is DeviceState.OPEN
        device.close()

    def test_sequence_length(self, device: Controller):
        """Triggers per armed sequence follow the schedule's frame count; not while armed."""
        device.set_sequence_length(12)  # closed: remembered, sent on open
        device.open()
        self.check_sequence_length(device, 12)
        device.set_sequence_length(9)
        assert device.frames_per_set == 9
        self.check_sequence_length(device, 9)
        device.arm()
        with pytest.raises(DeviceStateError):
            device.set_sequence_length(16)
        assert device.frames_per_set == 9
        device.disarm()
        for bad in (0, 2.5, 70000, True):
            with pytest.raises(ValueError, match="n_frames"):
                device.set_sequence_length(bad)
        device.close()

    def check_sequence_length(self, device: Controller, n_frames: int) -> None:
        """Backends that can show the device's own counter check it here."""

    def test_identify_when_closed_is_a_state_error(self, device: Controller):
        with pytest.raises(DeviceStateError):
            device.identify()

    def test_bad_led(self, device: Controller):
        with pytest.raises(ValueError, match="led"):
            device.set_led("uv")


__all__ = ["CameraContract", "ControllerContract", "ProjectorContract", "DeviceTimeout",
           "DeviceDisconnected"]
