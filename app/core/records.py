"""Typed records passed between layers: the instrument status, its devices, a calibration summary.

Plain frozen dataclasses; ``to_dict()`` gives the JSON object the REST API documents
(``GET /api/status``, ``GET /api/calibration``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal

#: running: depth maps arrive (one in the last 2 set periods); stalled: acquiring, but none do
State = Literal["starting", "calibrating", "running", "stalled", "stopped", "fault"]
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
    """The instrument's status (``GET /api/status``): state, rates, settings, counters.

    The counters (``sets_completed`` … ``faults``) count since start-up; ``warmup`` holds
    their values when the first depth map came (start-up losses: the camera running before
    the engine), ``since_warmup`` the difference (what the live session lost).
    """

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
    bit_depth: int | None = None  # the camera's significant bits (None: unknown)
    schedule: dict[str, Any] | None = None  # the fringe pattern schedule in use
    warnings: tuple[str, ...] = field(default=())
    sensor_noise: dict[str, Any] | None = None  # the camera noise model in use
    state_reason: str | None = None  # why the state is not running (or the start-up phase)
    phase: str | None = None  # start-up: "calibrating: board pose k of n", "compiling kernels", …
    progress: float | None = None  # of the phase, 0..1 (None: unknown)
    set_period_s: float | None = None  # one whole fringe set at the camera's frame period, s
    last_depth_age_s: float | None = None  # since the newest depth map, s (None: none yet)
    last_error_at: str | None = None  # when last_error happened, ISO 8601 UTC
    last_error_resolved: bool | None = None  # depth maps came after it (None: no error)
    groups_lost: int = 0  # frequency groups discarded for a missing or out-of-order frame
    patched_sets: int = 0  # sets completed with a group from an earlier projector cycle
    warmup: dict[str, int] = field(default_factory=dict)
    since_warmup: dict[str, int] = field(default_factory=dict)
    calibration_session: dict[str, Any] | None = None  # the wizard's open session: board, poses
    #: exposure bracketing when on: {"on", "auto", "exposures_ms": [base, long], "note"}; None off
    bracket: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        d = _shallow(self)
        d["calibration"] = None if self.calibration is None else self.calibration.to_dict()
        d["devices"] = [_shallow(dev) for dev in self.devices]
        d["warnings"] = list(self.warnings)
        return d


def _shallow(record: Any) -> dict[str, Any]:
    """Field name → value, one level (``dataclasses.asdict`` deep-copies: ten times slower here)."""
    return {f.name: getattr(record, f.name) for f in fields(record)}
