"""Build the devices typed backend specs ask for (devices are returned unopened).

The service layer turns its settings into these specs (:func:`app.service.devices.device_specs`);
nothing here reads settings.

``camera``: ``sim`` · ``opencv`` (``source`` = index, device path, URL or video
file) · ``genicam`` (``source`` = ``PRODUCER.cti[#DEVICE]``, DEVICE an index,
serial number or user-defined name) · ``replay`` (``source`` = recording folder).
``projector``: ``sim`` · ``lightcrafter`` (``host``/``port``) · ``none``.
``controller``: ``sim`` · ``serial`` (``port``: path, pyserial URL or
``usb:VID:PID[:SERIAL]``) · ``none``. Vendor and simulator modules are imported
only when chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, NamedTuple

from app.core.schedule import PatternSchedule
from app.devices.base import Camera, Controller, Projector

if TYPE_CHECKING:
    from app.devices.sim.world import SimulatedWorld


@dataclass(frozen=True)
class SimSpec:
    """The digital twin: rig preset, scene, noise seed, sensor bit depth (None: the rig's own),
    injected faults (rates per frame, period s)."""

    scene: str = "intestine_flap"
    seed: int | None = None
    bit_depth: int | None = 8
    drop_rate: float = 0.0
    timeout_rate: float = 0.0
    disconnect_every_s: float = 0.0
    realtime: bool = True
    rig: str = "default"
    cache_dir: str | None = None  # where the scene's traced geometry is kept between starts


@dataclass(frozen=True)
class CameraSpec:
    backend: Literal["sim", "opencv", "genicam", "replay"] = "sim"
    source: str = ""


@dataclass(frozen=True)
class ProjectorSpec:
    backend: Literal["sim", "lightcrafter", "none"] = "sim"
    host: str = "192.168.1.100"
    port: int = 21845


@dataclass(frozen=True)
class ControllerSpec:
    backend: Literal["sim", "serial", "none"] = "sim"
    port: str = ""


@dataclass(frozen=True)
class DeviceSpecs:
    """Which backend for each device, and the simulator's spec when any of them is ``sim``."""

    camera: CameraSpec = field(default_factory=CameraSpec)
    projector: ProjectorSpec = field(default_factory=ProjectorSpec)
    controller: ControllerSpec = field(default_factory=ControllerSpec)
    sim: SimSpec = field(default_factory=SimSpec)

    @property
    def all_sim(self) -> bool:
        return self.camera.backend == self.projector.backend == self.controller.backend == "sim"


class Devices(NamedTuple):
    camera: Camera
    projector: Projector | None
    controller: Controller | None
    world: SimulatedWorld | None = None  # the simulator's world, when any device is simulated


def _sim_devices(spec: SimSpec) -> Devices:
    from app.devices.sim import create_sim_devices

    built = create_sim_devices(
        scene=spec.scene, seed=spec.seed, bit_depth=spec.bit_depth, drop_rate=spec.drop_rate,
        timeout_rate=spec.timeout_rate, disconnect_every_s=spec.disconnect_every_s,
        realtime=spec.realtime, rig=spec.rig,
        cache_dir=None if spec.cache_dir is None else Path(spec.cache_dir),
    )
    return Devices(built.camera, built.projector, built.controller, built.world)


def _camera(spec: CameraSpec, schedule_length: int) -> Camera:
    source = spec.source.strip()
    if spec.backend == "opencv":
        from app.devices.opencv_camera import OpenCVCamera

        return OpenCVCamera(source or 0, schedule_length=schedule_length)
    if not source:
        raise ValueError(f"camera_source: required for camera = {spec.backend!r}")
    if spec.backend == "genicam":
        from app.devices.genicam_camera import GenICamCamera

        cti, _, device = source.partition("#")
        dev: int | str = int(device) if device.isdigit() else (device or 0)
        return GenICamCamera(cti, device=dev, schedule_length=schedule_length)
    if spec.backend == "replay":
        from app.devices.replay import ReplayCamera

        return ReplayCamera(source)
    raise ValueError(f"camera: unknown backend {spec.backend!r}")


def _projector(spec: ProjectorSpec) -> Projector | None:
    if spec.backend == "none":
        return None
    if spec.backend == "lightcrafter":
        from app.devices.lightcrafter import LightCrafterProjector

        return LightCrafterProjector(spec.host, spec.port)
    raise ValueError(f"projector: unknown backend {spec.backend!r}")


def _controller(spec: ControllerSpec) -> Controller | None:
    if spec.backend == "none":
        return None
    if spec.backend == "serial":
        if not spec.port.strip():
            raise ValueError("serial_port: required for controller = 'serial'")
        from app.devices.serial_controller import SerialController

        return SerialController(spec.port.strip())
    raise ValueError(f"controller: unknown backend {spec.backend!r}")


def create_devices(specs: DeviceSpecs) -> Devices:
    """Camera, projector (or None) and controller (or None) for ``specs``, not opened."""
    sim = None
    if "sim" in (specs.camera.backend, specs.projector.backend, specs.controller.backend):
        sim = _sim_devices(specs.sim)
    n = PatternSchedule().n_frames
    camera = (sim.camera if sim is not None and specs.camera.backend == "sim"
              else _camera(specs.camera, n))
    projector = (sim.projector if sim is not None and specs.projector.backend == "sim"
                 else _projector(specs.projector))
    controller = (sim.controller if sim is not None and specs.controller.backend == "sim"
                  else _controller(specs.controller))
    return Devices(camera, projector, controller, None if sim is None else sim.world)
