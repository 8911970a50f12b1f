"""The instrument's devices: creation from settings and the start/stop sequence."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from app.config import Settings
from app.core.records import DeviceStatus
from app.core.schedule import PatternSchedule
from app.devices.base import Camera, Controller, Device, DeviceState, Projector
from app.devices.factory import (
    CameraSpec,
    ControllerSpec,
    DeviceSpecs,
    ProjectorSpec,
    SimSpec,
)
from app.devices.factory import create_devices as factory_devices

if TYPE_CHECKING:
    from app.devices.sim.world import SimulatedWorld

log = logging.getLogger("fringescope.service.devices")


@dataclass
class DeviceBundle:
    """Camera (always), projector and controller (optional), and the simulator's world if any."""

    camera: Camera
    projector: Projector | None = None
    controller: Controller | None = None
    world: SimulatedWorld | None = None

    @property
    def is_sim(self) -> bool:
        return self.world is not None

    def all(self) -> list[Device]:
        return [d for d in (self.camera, self.projector, self.controller) if d is not None]

    def describe(self) -> tuple[DeviceStatus, ...]:
        return tuple(DeviceStatus(d.name, d.kind, d.state.value, d.last_error) for d in self.all())

    def faulted(self) -> bool:
        return any(d.state is DeviceState.FAULT for d in self.all())


def device_specs(settings: Settings) -> DeviceSpecs:
    """The typed backend specs the device factory takes, from ``settings``."""
    return DeviceSpecs(
        camera=CameraSpec(settings.camera, settings.camera_source),
        projector=ProjectorSpec(settings.projector, settings.lightcrafter_host,
                                settings.lightcrafter_port),
        controller=ControllerSpec(settings.controller, settings.serial_port),
        sim=SimSpec(
            scene=settings.sim_scene, seed=settings.sim_seed, bit_depth=settings.bit_depth,
            drop_rate=settings.sim_drop_rate, timeout_rate=settings.sim_timeout_rate,
            disconnect_every_s=settings.sim_disconnect_every_s, realtime=True, rig=settings.sim_rig,
            cache_dir=cache_dir(settings),
        ),
    )


def cache_dir(settings: Settings) -> str:
    """The folder of what the simulator rebuilds from parameters at every start."""
    if settings.cache_dir is not None:
        return str(settings.cache_dir)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return str(Path(base) / "fringescope")


def create_devices(settings: Settings) -> DeviceBundle:
    """Devices named by ``settings``; the simulator's world is kept when
    every device is simulated."""
    specs = device_specs(settings)
    devs = factory_devices(specs)
    return DeviceBundle(devs.camera, devs.projector, devs.controller,
                        devs.world if specs.all_sim else None)


def start_devices(
    devs: DeviceBundle, schedule: PatternSchedule, *, exposure_ms: float, led: str, bit_depth: int
) -> None:
    """Open every device and start the triggered sequence (camera first: it waits for triggers)."""
    for d in devs.all():
        d.open()
    devs.camera.configure(exposure_ms=exposure_ms, bit_depth=bit_depth)
    if devs.controller is not None:
        devs.controller.set_led(led)
        devs.controller.set_sequence_length(schedule.n_frames)
    if devs.projector is not None:
        devs.projector.set_led(led)
        devs.projector.load_schedule(schedule, exposure_ms=exposure_ms)
    devs.camera.start()
    if devs.controller is not None:
        devs.controller.arm()
    if devs.projector is not None:
        devs.projector.start()


def stop_devices(devs: DeviceBundle) -> None:
    """Stop the sequence, best effort (a faulted device is skipped, not raised)."""
    for stop in (
        getattr(devs.projector, "stop", None),
        getattr(devs.controller, "disarm", None),
        devs.camera.stop,
    ):
        if stop is None:
            continue
        try:
            stop()
        except Exception as exc:  # stopping must not fail shutdown
            log.warning("stop: %s", exc)


def close_devices(devs: DeviceBundle) -> None:
    stop_devices(devs)
    for d in devs.all():
        try:
            d.close()
        except Exception as exc:
            log.warning("close %s: %s", d.name, exc)


def apply_settings(devs: DeviceBundle, *, exposure_ms: float | None, led: str | None) -> None:
    """Change exposure and/or LED on running devices (called at a set boundary)."""
    if exposure_ms is not None:
        devs.camera.configure(exposure_ms=exposure_ms)
        if devs.projector is not None and devs.projector.state is not DeviceState.CLOSED:
            devs.projector.set_exposure(exposure_ms)  # timing only: the patterns stay uploaded
    if led is not None:
        if devs.controller is not None:
            devs.controller.set_led(led)
        if devs.projector is not None:
            devs.projector.set_led(led)
