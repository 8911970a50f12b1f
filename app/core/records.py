"""Typed records passed between layers: the instrument status, its devices, a calibration summary.

Plain frozen dataclasses; ``to_dict()`` gives the JSON object the REST API documents
(``GET /api/status``, ``GET /api/calibration``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal

State = Literal["starting", "calibrating", "running", "stopped", "fault"]
Mode = Literal["set", "rolling"]


@dataclass(frozen=True)
class CalibrationSummary:
    """The active calibration as the status and the calibration routes show it."""

    name: str | None
    created: str
    height_range_mm: tuple[float, float]
    image_size: tuple[int, int]
    software_version: str
    poses: int
    model: str = "eq5"  # the depth model: eq5 | geometric
    held_out: dict[str, dict[str, Any]] = field(default_factory=dict)  # per model: leave-one-pose-out errors

    def to_dict(self) -> dict[str, Any]:
        d = _shallow(self)
        d["height_range_mm"] = list(self.height_range_mm)
        d["image_size"] = list(self.image_size)
        return d


@dataclass(frozen=True)
class DeviceStatus:
    """One device: its name, kind (camera/projector/controller), state and last error."""

    name: str
    kind: str
    state: str
    error: str = ""


@dataclass(frozen=True)
class Status:
    """The instrument's status (``GET /api/status``): state, rates, settings, counters."""

    state: State
    camera_fps: float
    depth_fps: float
    latency_ms: float | None
    recon_ms: float | None
    exposure_ms: float
    led: str
    mode: Mode
    acquiring: bool
    calibration: CalibrationSummary | None
    devices: tuple[DeviceStatus, ...]
    last_error: str | None
    sets_completed: int
    results_published: int
    dropped_sets: int
    incomplete_sets: int
    mixed_sets: int
    frames_received: int
    frames_dropped: int
    faults: int
    recording: str | None
    bit_depth: int = 8  # the camera's significant bits
    schedule: dict[str, Any] = field(default_factory=dict)  # the fringe pattern schedule in use
    warnings: tuple[str, ...] = field(default=())
    sensor_noise: dict[str, Any] = field(default_factory=dict)  # the camera noise model in use

    def to_dict(self) -> dict[str, Any]:
        d = _shallow(self)
        d["calibration"] = None if self.calibration is None else self.calibration.to_dict()
        d["devices"] = [_shallow(dev) for dev in self.devices]
        d["warnings"] = list(self.warnings)
        return d


def _shallow(record: Any) -> dict[str, Any]:
    """Field name → value, one level (``dataclasses.asdict`` deep-copies: ten times slower here)."""
    return {f.name: getattr(record, f.name) for f in fields(record)}
