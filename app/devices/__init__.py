"""Hardware abstraction: cameras, projectors, LED/trigger controllers (sim and real)."""

from app.devices.base import (
    Camera,
    CameraCapabilities,
    CameraSettings,
    Controller,
    DeviceState,
    Frame,
    Projector,
)
from app.devices.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceStateError,
    DeviceTimeout,
    IncompleteSet,
    ProtocolError,
)

__all__ = [
    "Camera", "CameraCapabilities", "CameraSettings", "Controller", "DeviceState", "Frame",
    "Projector",
    "DeviceDisconnected", "DeviceError", "DeviceNotFound", "DeviceStateError", "DeviceTimeout",
    "IncompleteSet", "ProtocolError",
]
