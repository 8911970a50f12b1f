"""The device contract suite run against the three simulators."""

from __future__ import annotations

import pytest

from app.devices import DeviceState
from app.devices.sim import create_sim_devices
from tests.helpers.device_contract import CameraContract, ControllerContract, ProjectorContract


class _SimUnplug:
    supports_disconnect = True

    def disconnect(self, device):
        device.link.unplug()

    def reconnect(self, device):
        device.link.replug()


class TestSimulatedCamera(_SimUnplug, CameraContract):
    @pytest.fixture
    def device(self):
        dev = create_sim_devices(scene="plane", seed=0, realtime=False).camera
        yield dev
        dev.close()


class TestSimulatedProjector(_SimUnplug, ProjectorContract):
    @pytest.fixture
    def device(self):
        self.devs = create_sim_devices(scene="plane", seed=0, realtime=False)
        dev = self.devs.projector
        yield dev
        dev.close()
        self.devs.camera.close()

    def check_loaded(self, device, schedule):
        """The twin's camera then sees the new schedule's patterns, one cycle per its frame
        count."""
        assert self.devs.world.schedule == schedule
        if device.state is not DeviceState.RUNNING:
            return
        cam = self.devs.camera
        cam.open()
        cam.start()
        indices = [cam.grab(timeout_s=5.0).pattern_index for _ in range(schedule.n_frames + 1)]
        cam.close()
        first = indices[0]
        assert indices == [(first + i) % schedule.n_frames for i in range(schedule.n_frames + 1)]


class TestSimulatedController(_SimUnplug, ControllerContract):
    @pytest.fixture
    def device(self):
        dev = create_sim_devices(scene="plane", seed=0, realtime=False).controller
        yield dev
        dev.close()
