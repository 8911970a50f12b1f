"""The instrument's devices: creation from settings and the start/stop sequence."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from app.config import Settings
from app.devices.base import Camera, Controller, DeviceState, Projector
from app.recon.patterns import PatternSchedule

log = logging.getLogger("fringescope.service.devices")


@dataclass
class DeviceBundle:
    """Camera (always), projector and controller (optional), and the simulator's world if any."""

    camera: Camera
    projector: Projector | None = None
    controller: Controller | None = None
    world: Any = None

    @property
    def is_sim(self) -> bool:
        return self.world is not None

    def all(self) -> list[Any]:
        return [d for d in (self.camera, self.projector, self.controller) if d is not None]

    def describe(self) -> list[dict[str, Any]]:
        return [
            {"name": d.name, "kind": d.kind, "state": d.state.value, "error": d.last_error}
            for d in self.all()
        ]

    def faulted(self) -> bool:
        return any(d.state is DeviceState.FAULT for d in self.all())


def create_devices(settings: Settings) -> DeviceBundle:
    """Devices named by ``settings``: the simulator (keeping its world) or the factory's."""
    if settings.camera == "sim" and settings.projector == "sim" and settings.controller == "sim":
        from app.devices.sim import create_sim_devices

        sim = create_sim_devices(
            scene=settings.sim_scene,
            seed=settings.sim_seed,
            bit_depth=settings.bit_depth,
            drop_rate=settings.sim_drop_rate,
            timeout_rate=settings.sim_timeout_rate,
            disconnect_every_s=settings.sim_disconnect_every_s,
            realtime=True,
            rig=settings.sim_rig,
        )
        return DeviceBundle(sim.camera, sim.projector, sim.controller, sim.world)
    from app.devices.factory import create_devices as factory

    devs = factory(settings)
    return DeviceBundle(devs.camera, devs.projector, devs.controller, getattr(devs, "world", None))


def start_devices(
    devs: DeviceBundle, schedule: PatternSchedule, *, exposure_ms: float, led: str, bit_depth: int
) -> None:
    """Open every device and start the triggered sequence (camera first: it waits for triggers)."""
    for d in devs.all():
        d.open()
    devs.camera.configure(exposure_ms=exposure_ms, bit_depth=bit_depth)
    if devs.controller is not None:
        devs.controller.set_led(led)
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


def apply_settings(
    devs: DeviceBundle, schedule: PatternSchedule, *, exposure_ms: float | None, led: str | None
) -> None:
    """Change exposure and/or LED on running devices (called at a set boundary)."""
    if exposure_ms is not None:
        devs.camera.configure(exposure_ms=exposure_ms)
        if devs.projector is not None and devs.projector.state is not DeviceState.CLOSED:
            devs.projector.load_schedule(schedule, exposure_ms=exposure_ms)
    if led is not None:
        if devs.controller is not None:
            devs.controller.set_led(led)
        if devs.projector is not None:
            devs.projector.set_led(led)
