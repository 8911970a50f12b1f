"""The device contract suite run against the three simulators."""

from __future__ import annotations

import pytest

from app.devices.sim import create_sim_devices
from tests.devices.contract import CameraContract, ControllerContract, ProjectorContract


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
        dev = create_sim_devices(scene="plane", seed=0, realtime=False).projector
        yield dev
        dev.close()


class TestSimulatedController(_SimUnplug, ControllerContract):
    @pytest.fixture
    def device(self):
        dev = create_sim_devices(scene="plane", seed=0, realtime=False).controller
        yield dev
        dev.close()
