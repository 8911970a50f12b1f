"""Build the devices a :class:`~app.config.Settings` asks for (devices are returned unopened).

``camera``: ``sim`` · ``opencv`` (``camera_source`` = index, device path, URL or video
file) · ``genicam`` (``camera_source`` = ``PRODUCER.cti[#DEVICE]``, DEVICE an index,
serial number or user-defined name) · ``replay`` (``camera_source`` = recording folder).
``projector``: ``sim`` · ``lightcrafter`` (``lightcrafter_host``/``lightcrafter_port``) · ``none``.
``controller``: ``sim`` · ``serial`` (``serial_port``: path, pyserial URL or
``usb:VID:PID[:SERIAL]``) · ``none``. Vendor and simulator modules are imported
only when chosen.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from app.config import Settings
from app.devices.base import Camera, Controller, Projector
from app.recon.patterns import PatternSchedule


class Devices(NamedTuple):
    camera: Camera
    projector: Projector | None
    controller: Controller | None


def _sim_devices(settings: Settings) -> Devices:
    from app.devices.sim import create_sim_devices  # type: ignore[attr-defined,unused-ignore]

    built: Any = create_sim_devices(
        scene=settings.sim_scene, seed=settings.sim_seed, bit_depth=settings.bit_depth,
        drop_rate=settings.sim_drop_rate, timeout_rate=settings.sim_timeout_rate,
        disconnect_every_s=settings.sim_disconnect_every_s, rig=settings.sim_rig,
    )
    if isinstance(built, tuple) and not hasattr(built, "camera"):
        return Devices(*built)
    return Devices(built.camera, built.projector, built.controller)


def _camera(settings: Settings, schedule_length: int) -> Camera:
    source = settings.camera_source.strip()
    if settings.camera == "opencv":
        from app.devices.opencv_camera import OpenCVCamera

        return OpenCVCamera(source or 0, schedule_length=schedule_length)
    if not source:
        raise ValueError(f"camera_source: required for camera = {settings.camera!r}")
    if settings.camera == "genicam":
        from app.devices.genicam_camera import GenICamCamera

        cti, _, device = source.partition("#")
        dev: int | str = int(device) if device.isdigit() else (device or 0)
        return GenICamCamera(cti, device=dev, schedule_length=schedule_length)
    if settings.camera == "replay":
        from app.devices.replay import ReplayCamera

        return ReplayCamera(source)
    raise ValueError(f"camera: unknown backend {settings.camera!r}")


def _projector(settings: Settings) -> Projector | None:
    if settings.projector == "none":
        return None
    if settings.projector == "lightcrafter":
        from app.devices.lightcrafter import LightCrafterProjector

        return LightCrafterProjector(settings.lightcrafter_host, settings.lightcrafter_port)
    raise ValueError(f"projector: unknown backend {settings.projector!r}")


def _controller(settings: Settings) -> Controller | None:
    if settings.controller == "none":
        return None
    if settings.controller == "serial":
        if not settings.serial_port.strip():
            raise ValueError("serial_port: required for controller = 'serial'")
        from app.devices.serial_controller import SerialController

        return SerialController(settings.serial_port.strip())
    raise ValueError(f"controller: unknown backend {settings.controller!r}")


def create_devices(settings: Settings) -> Devices:
    """Camera, projector (or None) and controller (or None) for ``settings``, not opened."""
    sim = None
    if "sim" in (settings.camera, settings.projector, settings.controller):
        sim = _sim_devices(settings)
    n = PatternSchedule().n_frames
    camera = sim.camera if sim is not None and settings.camera == "sim" else _camera(settings, n)
    projector = sim.projector if sim is not None and settings.projector == "sim" else _projector(settings)
    controller = sim.controller if sim is not None and settings.controller == "sim" else _controller(settings)
    return Devices(camera, projector, controller)
