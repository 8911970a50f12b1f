"""create_devices: typed backend specs → unopened devices of the chosen backends."""

from __future__ import annotations

import pytest

from app.devices import DeviceState
from app.devices.factory import (
    CameraSpec,
    ControllerSpec,
    Devices,
    DeviceSpecs,
    ProjectorSpec,
    SimSpec,
    create_devices,
)
from app.devices.genicam_camera import GenICamCamera
from app.devices.lightcrafter import LightCrafterProjector
from app.devices.opencv_camera import OpenCVCamera
from app.devices.replay import ReplayCamera
from app.devices.serial_controller import SerialController
from tests.helpers.recordings import make_recording


def test_real_backends_are_built_unopened(tmp_path):
    rec = make_recording(tmp_path / "rec", n_sets=1)
    devs = create_devices(
        DeviceSpecs(
            CameraSpec("replay", str(rec)),
            ProjectorSpec("lightcrafter", "10.0.0.7", 2000),
            ControllerSpec("serial", "usb:2341:0043:FS0001"),
        )
    )
    assert isinstance(devs, Devices)
    assert isinstance(devs.camera, ReplayCamera) and devs.camera.folder == rec
    assert isinstance(devs.projector, LightCrafterProjector)
    assert (devs.projector.host, devs.projector.port) == ("10.0.0.7", 2000)
    assert (
        isinstance(devs.controller, SerialController)
        and devs.controller.port == "usb:2341:0043:FS0001"
    )
    assert devs.world is None
    assert all(d.state is DeviceState.CLOSED for d in devs[:3])
    # the replay camera really works from these settings
    devs.camera.open()
    devs.camera.start()
    assert devs.camera.grab(1.0).pattern_index == 0
    devs.camera.close()


NONE = {"projector": ProjectorSpec("none"), "controller": ControllerSpec("none")}


def test_camera_sources_and_none(tmp_path):
    devs = create_devices(DeviceSpecs(CameraSpec("opencv", "2"), **NONE))
    assert isinstance(devs.camera, OpenCVCamera) and devs.camera.source == 2
    assert devs.projector is None and devs.controller is None
    devs = create_devices(DeviceSpecs(CameraSpec("opencv", "rtsp://cam/stream"), **NONE))
    assert devs.camera.source == "rtsp://cam/stream"
    cam = create_devices(DeviceSpecs(CameraSpec("genicam", "/opt/x.cti#3"), **NONE)).camera
    assert isinstance(cam, GenICamCamera) and str(cam.cti) == "/opt/x.cti" and cam.device == 3
    cam = create_devices(DeviceSpecs(CameraSpec("genicam", "/opt/x.cti#SN42"), **NONE)).camera
    assert cam.device == "SN42"


@pytest.mark.parametrize(
    ("camera", "controller", "field"),
    [(CameraSpec("replay"), ControllerSpec("none"), "camera_source"),
     (CameraSpec("genicam"), ControllerSpec("none"), "camera_source"),
     (CameraSpec("replay", "x"), ControllerSpec("serial"), "serial_port"),
     (CameraSpec("replay", "x"), ControllerSpec("serial", "usb:12"), "port")],
)
def test_missing_or_bad_specs_name_the_field(camera, controller, field):
    with pytest.raises(ValueError, match=field):
        create_devices(DeviceSpecs(camera, ProjectorSpec("none"), controller))


def test_sim_backends_come_from_the_simulator():
    specs = DeviceSpecs(
        CameraSpec("sim"), ProjectorSpec("sim"), ControllerSpec("none"), SimSpec(seed=1)
    )
    assert not specs.all_sim
    devs = create_devices(specs)
    assert (
        devs.camera.kind == "camera"
        and devs.projector is not None
        and devs.projector.kind == "projector"
    )
    assert devs.controller is None and devs.world is not None
    assert all(d.state is DeviceState.CLOSED for d in devs[:3] if d is not None)
