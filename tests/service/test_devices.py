"""Settings → typed device specs (the service layer is the only one reading settings)."""

from __future__ import annotations

from app.config import Settings
from app.devices.factory import CameraSpec, ControllerSpec, ProjectorSpec
from app.service.devices import create_devices, device_specs


def test_specs_carry_every_device_setting():
    s = Settings(
        camera="genicam",
        camera_source="/opt/x.cti#2",
        projector="lightcrafter",
        lightcrafter_host="10.1.2.3",
        lightcrafter_port=4000,
        controller="serial",
        serial_port="/dev/ttyACM1",
        sim_scene="plane",
        sim_seed=5,
        bit_depth=12,
        sim_drop_rate=0.25,
        sim_timeout_rate=0.125,
        sim_disconnect_every_s=3.0,
    )
    specs = device_specs(s)
    assert specs.camera == CameraSpec("genicam", "/opt/x.cti#2")
    assert specs.projector == ProjectorSpec("lightcrafter", "10.1.2.3", 4000)
    assert specs.controller == ControllerSpec("serial", "/dev/ttyACM1")
    assert (specs.sim.scene, specs.sim.seed, specs.sim.bit_depth) == ("plane", 5, 12)
    assert (specs.sim.drop_rate, specs.sim.timeout_rate, specs.sim.disconnect_every_s) == (
        0.25,
        0.125,
        3.0,
    )
    assert not specs.all_sim and device_specs(Settings()).all_sim


def test_world_kept_only_when_every_device_is_simulated():
    assert create_devices(Settings(sim_seed=1)).is_sim
    assert not create_devices(Settings(sim_seed=1, controller="none")).is_sim
