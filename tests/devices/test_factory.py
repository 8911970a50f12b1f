"""create_devices: Settings → unopened devices of the chosen backends."""

from __future__ import annotations

import importlib

import pytest

from app.config import Settings
from app.devices import DeviceState
from app.devices.factory import Devices, create_devices
from app.devices.genicam_camera import GenICamCamera
from app.devices.lightcrafter import LightCrafterProjector
from app.devices.opencv_camera import OpenCVCamera
from app.devices.replay import ReplayCamera
from app.devices.serial_controller import SerialController
from tests.devices.test_replay import make_recording


def test_real_backends_are_built_unopened(tmp_path):
    rec = make_recording(tmp_path / "rec", n_sets=1)
    s = Settings(camera="replay", camera_source=str(rec), projector="lightcrafter", lightcrafter_host="10.0.0.7",
                 lightcrafter_port=2000, controller="serial", serial_port="usb:2341:0043:FS0001")
    devs = create_devices(s)
    assert isinstance(devs, Devices)
    assert isinstance(devs.camera, ReplayCamera) and devs.camera.folder == rec
    assert isinstance(devs.projector, LightCrafterProjector)
    assert (devs.projector.host, devs.projector.port) == ("10.0.0.7", 2000)
    assert isinstance(devs.controller, SerialController) and devs.controller.port == "usb:2341:0043:FS0001"
    assert all(d.state is DeviceState.CLOSED for d in devs)
    # the replay camera really works from these settings
    devs.camera.open()
    devs.camera.start()
    assert devs.camera.grab(1.0).pattern_index == 0
    devs.camera.close()


def test_camera_sources_and_none(tmp_path):
    devs = create_devices(Settings(camera="opencv", camera_source="2", projector="none", controller="none"))
    assert isinstance(devs.camera, OpenCVCamera) and devs.camera.source == 2
    assert devs.projector is None and devs.controller is None
    devs = create_devices(Settings(camera="opencv", camera_source="rtsp://cam/stream", projector="none",
                                   controller="none"))
    assert devs.camera.source == "rtsp://cam/stream"
    cam = create_devices(Settings(camera="genicam", camera_source="/opt/x.cti#3", projector="none",
                                  controller="none")).camera
    assert isinstance(cam, GenICamCamera) and str(cam.cti) == "/opt/x.cti" and cam.device == 3
    cam = create_devices(Settings(camera="genicam", camera_source="/opt/x.cti#SN42", projector="none",
                                  controller="none")).camera
    assert cam.device == "SN42"


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"camera": "replay"}, "camera_source"), ({"camera": "genicam"}, "camera_source"),
     ({"camera": "replay", "camera_source": "x", "controller": "serial"}, "serial_port"),
     ({"camera": "replay", "camera_source": "x", "controller": "serial", "serial_port": "usb:12"}, "port")],
)
def test_missing_or_bad_settings_name_the_field(kwargs, field):
    base = {"projector": "none", "controller": "none"}
    with pytest.raises(ValueError, match=field):
        create_devices(Settings(**{**base, **kwargs}))


def test_sim_backends_come_from_the_simulator():
    sim = importlib.import_module("app.devices.sim")
    if not hasattr(sim, "create_sim_devices"):
        pytest.skip("app.devices.sim.create_sim_devices not available yet")
    devs = create_devices(Settings(camera="sim", projector="sim", controller="none", sim_seed=1))
    assert devs.camera.kind == "camera" and devs.projector is not None and devs.projector.kind == "projector"
    assert devs.controller is None
    assert all(d.state is DeviceState.CLOSED for d in devs if d is not None)
