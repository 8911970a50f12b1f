"""Typed records passed between layers: the instrument status, its devices, a calibration summary.

Plain frozen dataclasses, the one definition of each field: its type, its default and (in
``metadata["description"]``) what it means. ``to_dict()`` gives the JSON object the REST API
documents (``GET /api/status``, ``GET /api/calibration``); the API's response models are
derived from these records (``app/api/schemas.py``), so a field is written once.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal

#: running: depth maps arrive (one in the last 2 set periods); stalled: acquiring, but none do
State = Literal["starting", "calibrating", "running", "stalled", "stopped", "fault"]
Mode = Literal["set", "rolling"]
#: per depth model, its leave-one-pose-out height errors (rms_mm, max_mm, points, …)
HeldOut = dict[str, dict[str, float | int | str | None]]


def doc(text: str) -> dict[str, str]:
    """A field's ``metadata``: its description (the API's schema shows it)."""
    return {"description": text}


@dataclass(frozen=True)
class CalibrationSummary:
    """The active calibration as the status and the calibration routes show it."""

    name: str | None
    created: str
    height_range_mm: tuple[float, float]
    image_size: tuple[int, int]
    software_version: str
    poses: int
    model: str = field(default="eq5", metadata=doc("active depth model: eq5 | geometric"))
    held_out: HeldOut = field(default_factory=dict, metadata=doc(
        "per model, leave-one-pose-out height errors (rms_mm, max_mm, points)"))

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
class Alarm:
    """A fault the user must acknowledge: it stays on the dashboard until then."""

    id: int = field(metadata=doc("the alarm's number, for POST /api/alarms/{id}/ack"))
    source: str = field(metadata=doc("the part that raised it, e.g. recorder"))
    message: str
    raised_at: str = field(metadata=doc("ISO 8601 UTC"))
    acknowledged_at: str | None = field(default=None, metadata=doc(
        "ISO 8601 UTC; null: still shown"))

    def to_dict(self) -> dict[str, Any]:
        return _shallow(self)


@dataclass(frozen=True)
class Bracket:
    """Live exposure bracketing while it is on: sets alternate between two exposures."""

    on: bool
    auto: bool = field(metadata=doc(
        "switched on by the auto-exposure (the scene spans more than one exposure)"))
    exposures_ms: tuple[float, ...] = field(metadata=doc(
        "[the exposure, the +2 stop one], ms"))
    note: str

    def to_dict(self) -> dict[str, Any]:
        d = _shallow(self)
        d["exposures_ms"] = list(self.exposures_ms)
        return d


@dataclass(frozen=True)
class Status:
    """The instrument's status (``GET /api/status``): state, rates, settings, counters.

    The counters (``sets_completed`` … ``faults``) count since start-up; ``warmup`` holds
    their values when the first depth map came (start-up losses: the camera running before
    the engine), ``since_warmup`` the difference (what the live session lost).
    """

    state: State = field(metadata=doc(
        "running only while depth maps arrive (one in the last 2 set periods); "
        "else why in state_reason"))
    camera_fps: float
    depth_fps: float
    latency_ms: float | None = field(metadata=doc(
        "median, newest frame arrival → result published"))
    recon_ms: float | None = field(metadata=doc("median reconstruction time per set"))
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
    recording: str | None = field(metadata=doc("name of the running recording"))
    bit_depth: int | None = field(default=None, metadata=doc(
        "the camera's significant bits (null: unknown)"))
    schedule: dict[str, Any] | None = field(default=None, metadata=doc(
        "the fringe pattern schedule in use"))
    warnings: tuple[str, ...] = field(default=())
    sensor_noise: dict[str, Any] | None = field(default=None, metadata=doc(
        "the camera noise model σ and the validity rule use: source (measured | nominal), "
        "read_noise_dn, gain_dn_per_e, estimates; the projector-gamma correction of the newest "
        "depth map, phase_error (learned: the calibration's table; measured: the live sets' "
        "own; set: that set's own, before the first live estimate; none; null: no map yet), "
        "and gamma_table_rms_rad, the RMS of the live sets' table (null: none)"))
    state_reason: str | None = field(default=None, metadata=doc(
        "why the state is not running, or the start-up phase; while running, "
        "what slows the depth rate (exposure bracketing)"))
    phase: str | None = field(default=None, metadata=doc(
        "start-up phase: 'calibrating pose k of n', 'compiling kernels', …; "
        "null once depth maps come"))
    progress: float | None = field(default=None, metadata=doc(
        "progress of the phase, 0..1 (null: unknown)"))
    set_period_s: float | None = field(default=None, metadata=doc(
        "one whole fringe set at the camera's frame period, s"))
    last_depth_age_s: float | None = field(default=None, metadata=doc(
        "seconds since the newest depth map (null: none)"))
    last_error_at: str | None = field(default=None, metadata=doc(
        "when last_error happened, ISO 8601 UTC"))
    last_error_resolved: bool | None = field(default=None, metadata=doc(
        "depth maps came after last_error (null: no error)"))
    groups_lost: int = field(default=0, metadata=doc(
        "frequency groups discarded for a missing or out-of-order frame"))
    patched_sets: int = field(default=0, metadata=doc(
        "sets completed with a group from an earlier projector cycle"))
    warmup: dict[str, int] = field(default_factory=dict, metadata=doc(
        "the counters when the first depth map came (start-up losses)"))
    since_warmup: dict[str, int] = field(default_factory=dict, metadata=doc(
        "the counters since the first depth map"))
    calibration_session: dict[str, Any] | None = field(default=None, metadata=doc(
        "the open calibration session (board, created, poses, solved) or null"))
    alarms: tuple[Alarm, ...] = field(default=(), metadata=doc(
        "alarms not yet acknowledged, oldest first (POST /api/alarms/{id}/ack)"))
    bracket: Bracket | None = field(default=None, metadata=doc(
        "exposure bracketing while on (each map fuses two sets: half the depth rate); "
        "null when off"))

    def to_dict(self) -> dict[str, Any]:
        d = _shallow(self)
        d["calibration"] = None if self.calibration is None else self.calibration.to_dict()
        d["devices"] = [_shallow(dev) for dev in self.devices]
        d["warnings"] = list(self.warnings)
        d["alarms"] = [a.to_dict() for a in self.alarms]
        d["bracket"] = None if self.bracket is None else self.bracket.to_dict()
        return d


def _shallow(record: Any) -> dict[str, Any]:
    """Field name → value, one level (``dataclasses.asdict`` deep-copies: ten times slower)."""
    return {f.name: getattr(record, f.name) for f in fields(record)}
