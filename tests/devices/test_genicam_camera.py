"""GenICam camera through harvesters and the simulated GenTL producer shipped in the ``genicam``
wheel."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.devices import DeviceError, DeviceNotFound, DeviceState, DeviceTimeout
from app.devices.genicam_camera import GenICamCamera

genicam = pytest.importorskip("genicam", reason="optional GenICam extra (genicam) not installed")
pytest.importorskip("harvesters", reason="optional GenICam extra (harvesters) not installed")
VIKY = Path(genicam.__file__).parent / "viky.cti"
if not VIKY.is_file():
    pytest.skip(
        f"simulated GenTL producer {VIKY} not shipped by this genicam build",
        allow_module_level=True,
    )


def test_frames_from_the_simulated_producer():
    cam = GenICamCamera(VIKY, device="1", schedule_length=4)  # by serial number
    caps = cam.capabilities
    assert (caps.width, caps.height) == (400, 400) and caps.bit_depths == (8,)
    assert not caps.hardware_trigger  # viky has no trigger nodes
    cam.open()
    cam.start()
    frames = [cam.grab(timeout_s=3.0) for _ in range(5)]
    cam.close()
    for f in frames:
        assert f.data.shape == (400, 400) and f.data.dtype == np.uint8
    assert [f.pattern_index for f in frames] == [0, 1, 2, 3, 0]
    assert [f.index for f in frames] == list(range(5))
    assert len({f.data.tobytes() for f in frames}) > 1  # a moving scene, not one frame repeated


def test_slow_camera_times_out():
    cam = GenICamCamera(VIKY)
    cam.open()
    # the simulated producer has no exposure control: its frame rate is what makes it slow
    cam._ia.remote_device.node_map.AcquisitionFrameRate.value = 1.0
    cam.start()
    cam.grab(timeout_s=3.0)
    with pytest.raises(DeviceTimeout):
        cam.grab(timeout_s=0.2)
    cam.close()


def test_hardware_trigger_refused_without_trigger_nodes():
    cam = GenICamCamera(VIKY, hardware_trigger=True)
    cam_free = GenICamCamera(VIKY)
    with pytest.raises(DeviceError, match="no hardware trigger"):
        cam.open()
    assert cam.state is DeviceState.CLOSED
    cam_free.open()  # the failed open released the camera: it can be opened again
    cam_free.close()


def test_missing_producer_and_camera(tmp_path):
    with pytest.raises(DeviceNotFound):
        GenICamCamera(tmp_path / "missing.cti").open()
    with pytest.raises(DeviceNotFound):
        GenICamCamera(VIKY, device=7).open()
    with pytest.raises(DeviceNotFound):
        GenICamCamera(VIKY, device="no-such-serial").open()
