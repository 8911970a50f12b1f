"""The device contract (tests/helpers/device_contract.py) run against every real-hardware backend,
each over a real transport: pty, TCP socket, video file, capture-set folders, GenTL producer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.devices.controller_emulator import PtyControllerEmulator
from app.devices.genicam_camera import GenICamCamera
from app.devices.lightcrafter import LightCrafterProjector, sequence_bit_depth
from app.devices.lightcrafter_emulator import LightCrafterEmulator
from app.devices.opencv_camera import OpenCVCamera
from app.devices.replay import ReplayCamera
from app.devices.serial_controller import SerialController
from app.recon.patterns import generate_patterns
from tests.helpers.device_contract import CameraContract, ControllerContract, ProjectorContract
from tests.helpers.recordings import make_recording
from tests.helpers.videos import write_video


class TestSerialControllerContract(ControllerContract):
    supports_disconnect = True

    @pytest.fixture
    def device(self, tmp_path):
        self.emu = PtyControllerEmulator(tmp_path / "ttyFRINGE").start()
        dev = SerialController(self.emu.port, reset_wait_s=0.02, watchdog_ms=400, timeout_s=0.3)
        yield dev
        dev.close()
        self.emu.stop()

    def check_sequence_length(self, device, n_frames):
        assert self.emu.protocol.settings["count"] == n_frames  # TCNT reached the firmware

    def disconnect(self, device):
        self.emu.vanish()

    def reconnect(self, device):
        self.emu.reappear()


class TestLightCrafterContract(ProjectorContract):
    supports_disconnect = True

    @pytest.fixture
    def device(self):
        self.emu = LightCrafterEmulator().start()
        dev = LightCrafterProjector(self.emu.host, self.emu.port, timeout_s=1.0)
        yield dev
        dev.close()
        self.emu.stop()

    def check_loaded(self, device, schedule):
        st = self.emu.state
        bits = sequence_bit_depth(schedule.n_frames)
        assert st.sequence["count"] == schedule.n_frames and st.sequence["bit_depth"] == bits
        # the device shows the least significant bits: levels 0 … 2**bits − 1 (DLPU007A §3.11)
        expected = np.round(generate_patterns(schedule) * ((2**bits - 1) / 255))
        assert all(np.array_equal(st.patterns[i], expected[i]) for i in range(schedule.n_frames))

    def disconnect(self, device):
        self.emu.stop()

    def reconnect(self, device):
        self.emu.start()  # same port: SO_REUSEADDR


class TestOpenCVCameraContract(CameraContract):
    # a video file cannot be unplugged; live-source unplug needs a UVC device

    @pytest.fixture
    def device(self, tmp_path):
        dev = OpenCVCamera(str(write_video(tmp_path / "v.avi")), fps=0)
        yield dev
        dev.close()


class TestReplayCameraContract(CameraContract):
    supports_disconnect = True

    @pytest.fixture
    def device(self, tmp_path):
        self.rec = make_recording(tmp_path / "rec")
        self.away = tmp_path / "unplugged"
        dev = ReplayCamera(self.rec, pace=False)
        yield dev
        dev.close()

    def disconnect(self, device):
        self.rec.rename(self.away)  # like a USB disk pulled mid-replay

    def reconnect(self, device):
        self.away.rename(self.rec)


def _viky() -> Path | None:
    try:
        import genicam
        import harvesters  # noqa: F401
    except ImportError:
        return None
    path = Path(genicam.__file__).parent / "viky.cti"
    return path if path.is_file() else None


@pytest.mark.skipif(
    _viky() is None, reason="no simulated GenTL producer (genicam's viky.cti) installed"
)
class TestGenICamCameraContract(CameraContract):
    @pytest.fixture
    def device(self):
        dev = GenICamCamera(_viky() or "")
        yield dev
        dev.close()
