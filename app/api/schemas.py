"""Request and response bodies of the REST API (pydantic; out-of-range input → 422)."""

from __future__ import annotations

import dataclasses
import functools
import operator
from collections.abc import Mapping
from types import UnionType
from typing import (
    TYPE_CHECKING,
    Annotated,
    Any,
    Literal,
    Union,
    get_args,
    get_origin,
    get_type_hints,
)

from pydantic import (
    AliasChoices,
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    ValidationInfo,
    create_model,
    field_validator,
    model_validator,
)
from pydantic.json_schema import SkipJsonSchema
from pydantic_core import PydanticCustomError

from app.analysis.measure import EXACT_POINTS, MIN_POINTS
from app.capture.recording import NAME_PATTERN
from app.core import records
from app.core.calibration import FORMAT as CALIBRATION_FORMAT
from app.core.calibration import FORMAT_V1 as CALIBRATION_FORMAT_V1
from app.core.limits import EXPOSURE_RANGE_MS, Led
from app.core.records import DeviceStatus, Status
from app.recon.exposure import DEFAULT_SATURATION_LIMIT
from app.recon.reconstructor import PhaseErrorSource

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

# checked here (the API boundary) and by the devices
EXPOSURE_MIN_MS, EXPOSURE_MAX_MS = EXPOSURE_RANGE_MS


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _integer_nesting(annotation: object) -> int | None:
    """How deep the integers sit in ``annotation`` (``int`` 0, ``list[int]`` 1, …); None when
    it holds none. ``X | None`` is read as ``X``; ``bool`` is not an integer here."""
    if annotation is int:
        return 0
    origin, args = get_origin(annotation), get_args(annotation)
    if origin is Annotated:
        return _integer_nesting(args[0])
    if origin in (Union, UnionType):
        depths = {_integer_nesting(a) for a in args if a is not type(None)}
        return depths.pop() if len(depths) == 1 else None
    if origin is list and args:
        inner = _integer_nesting(args[0])
        return None if inner is None else inner + 1
    return None


def _refuse_non_numbers(value: object, nesting: int) -> None:
    if nesting == 0:
        if isinstance(value, (bool, str)):
            what = "a boolean" if isinstance(value, bool) else "a string"
            raise PydanticCustomError("int_type", "must be a JSON integer, not {what}",
                                      {"what": what})
    elif isinstance(value, list):
        for item in value:
            _refuse_non_numbers(item, nesting - 1)


def integers_are_numbers(*fields: str) -> Any:
    """A validator for a body's integer ``fields``: ``false`` is not 0 nor ``"5"`` 5 (lax
    parsing reads them so). Not ``strict=True``, which also refuses ``19.0`` (an integer to
    JSON Schema), nor an annotated validator, which hides the bounds from the OpenAPI document;
    and per field, since a before-validator may not touch a union's discriminator."""

    def check(cls: type[BaseModel], value: Any, info: ValidationInfo) -> Any:
        nesting = _integer_nesting(cls.model_fields[info.field_name or ""].annotation)
        if nesting is None:
            raise TypeError(f"{cls.__name__}.{info.field_name} holds no integers")
        _refuse_non_numbers(value, nesting)
        return value

    return field_validator(*fields, mode="before")(classmethod(check))


class ExposureIn(Strict):
    exposure_ms: float = Field(..., strict=True, ge=EXPOSURE_MIN_MS, le=EXPOSURE_MAX_MS,
                               description="camera exposure, "
                                           f"{EXPOSURE_MIN_MS:g}–{EXPOSURE_MAX_MS:g} ms")


class ExposureOut(BaseModel):
    exposure_ms: float
    applies: str = "from the next whole fringe set"


class AutoExposureIn(Strict):
    saturation_limit: float = Field(DEFAULT_SATURATION_LIMIT, strict=True, ge=0.0, lt=1.0,
                                    description="allowed saturated fraction")
    max_exposure_ms: float = Field(EXPOSURE_MAX_MS, strict=True, ge=EXPOSURE_MIN_MS,
                                   le=EXPOSURE_MAX_MS)


class ExposureTrialOut(BaseModel):
    exposure_ms: float
    saturated_fraction: float
    modulation: float


class AutoExposureOut(BaseModel):
    exposure_ms: float
    saturated_fraction: float
    modulation: float
    saturation_limit: float
    trials: list[ExposureTrialOut]
    warning: str | None = None
    bracket: bool = Field(False, description="exposure bracketing is on: the scene's lit pixels "
                                             "invalid for low signal exceed the share below")
    low_signal_share: float | None = Field(
        None, description="share of lit, unsaturated pixels invalid for low signal at the chosen "
                          "exposure (null: no calibration to judge with)")


class LedIn(Strict):
    led: Led


class LedOut(BaseModel):
    led: str
    applies: str = "from the next whole fringe set"


class ModeIn(Strict):
    # at least one of the two (the document says so: minProperties), neither null
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False,
                              json_schema_extra={"minProperties": 1})

    rolling: StrictBool | SkipJsonSchema[None] = Field(
        None, description="a depth map after every frequency group")
    bracket: StrictBool | SkipJsonSchema[None] = Field(
        None, description="exposure bracketing: whole sets alternate between the exposure and "
                          "+2 stops, fused per pixel (set mode only; half the depth rate)")

    @model_validator(mode="after")
    def _given_and_not_null(self) -> ModeIn:
        for name in ("rolling", "bracket"):
            if name in self.model_fields_set and getattr(self, name) is None:
                raise ValueError(f"{name}: must be true or false, not null")
        if self.rolling is None and self.bracket is None:
            raise ValueError("give rolling and/or bracket")
        return self


class ModeOut(BaseModel):
    mode: Literal["set", "rolling"]
    bracket: bool = Field(description="exposure bracketing is on")


class AcquisitionOut(BaseModel):
    acquiring: bool
    state: str


def _api_type(tp: object, models: Mapping[type, type[BaseModel]]) -> object:
    """A record field's type as the API states it: tuples are JSON arrays, records their models."""
    if isinstance(tp, type) and tp in models:
        return models[tp]
    args = get_args(tp)
    if get_origin(tp) is tuple:
        items = {a for a in args if a is not Ellipsis}
        if len(items) != 1:
            raise TypeError(f"tp: a record's tuple holds one item type, got {tp!r}")
        return list[_api_type(items.pop(), models)]  # type: ignore[misc]  # built at run time
    if get_origin(tp) in (Union, UnionType):
        return functools.reduce(operator.or_, (_api_type(a, models) for a in args))
    return tp


def _api_default(value: object) -> object:
    return list(value) if isinstance(value, tuple) else value


def model_of(record: type[DataclassInstance], name: str,
             models: Mapping[type, type[BaseModel]] | None = None) -> type[BaseModel]:
    """The response model ``name`` of a ``core.records`` dataclass: the record's fields, types,
    defaults and descriptions (``metadata["description"]``), in its order; records nested in
    it become the models in ``models``."""
    hints = get_type_hints(record, include_extras=True)
    nested = models or {}
    spec: dict[str, Any] = {}
    for f in dataclasses.fields(record):
        description = f.metadata.get("description")
        if f.default is not dataclasses.MISSING:
            info = Field(_api_default(f.default), description=description)
        elif f.default_factory is not dataclasses.MISSING:
            info = Field(default_factory=f.default_factory, description=description)
        else:
            info = Field(description=description)
        spec[f.name] = (_api_type(hints[f.name], nested), info)
    return create_model(name, __doc__=record.__doc__, **spec)


DeviceOut = model_of(DeviceStatus, "DeviceOut")
CalibrationSummary = model_of(records.CalibrationSummary, "CalibrationSummary")
AlarmOut = model_of(records.Alarm, "AlarmOut")
BracketOut = model_of(records.Bracket, "BracketOut")
StatusOut = model_of(Status, "StatusOut", {records.CalibrationSummary: CalibrationSummary,
                                           DeviceStatus: DeviceOut, records.Alarm: AlarmOut,
                                           records.Bracket: BracketOut})


class ResultMeta(BaseModel):
    seq: int
    mode: str
    created: str
    exposure_ms: float
    led: str
    frame_indices: list[int]
    timestamps: list[float]
    latency_ms: float
    recon_ms: float
    valid_fraction: float
    shape: list[int]
    bracket_exposures_ms: list[float] | None = Field(
        None, description="exposure bracketing: the two sets' exposures this map fuses "
                          "(null: one set)")
    map_time: float | None = Field(None, description="the instant the depth stands for (frame "
                                                     "timestamp clock, s): its finest frequency "
                                                     "group's mid-exposure")
    moved_pixels: int = Field(0, description="pixels invalid for motion (frequency groups' "
                                             "backgrounds disagree)")
    motion_ms: float = Field(0.0, description="of recon_ms, the motion test")
    scene_moved: bool = Field(False, description="the set's raw motion flags exceed a still "
                                                 "scene's: valid pixels then need σ ≤ "
                                                 "gross_error_mm / (z + k)")
    uncertain_moving_pixels: int = Field(0, description="valid pixels made UNCERTAIN by that "
                                                        "moving-scene σ bound")


class PhaseSummary(BaseModel):
    """``POST /api/phase``: calibration-free decoding of an uploaded capture set."""

    valid_fraction: float
    phase_min_rad: float | None
    phase_max_rad: float | None
    recovered_pixels: int = Field(description="pixels with clipped samples fitted "
                                              "from the unclipped ones")
    bit_depth: int
    schedule: dict[str, Any]
    shape: list[int]


class ReconstructSummary(BaseModel):
    valid_fraction: float
    height_min_mm: float | None
    height_max_mm: float | None
    elapsed_ms: float
    shape: list[int]
    noise_source: Literal["given", "set", "nominal"] = Field(
        description="camera noise behind σ and the validity rule: fitted to the set (N > 3) or the "
                    "nominal sensor where the set cannot give it (noise_note says why)")
    noise_note: str = ""
    phase_error_source: PhaseErrorSource = Field(
        "none", description="the projector-gamma phase-error table the wrapped phases were "
                            "corrected with: the calibration's learned one, or the set's own "
                            "(an N = 4 set whose projector departs from a sinusoid), or none")
    read_noise_dn: float = Field(description="the noise model's signal-independent σ, DN")
    gain_dn_per_e: float = Field(description="the noise model's shot-noise gain, DN per electron")
    sigma_median_mm: float | None = Field(
        None, description="median over valid pixels of the total 1-σ, mm (sensor noise ⊕ "
                          "calibration; ?format=npy&field=sigma: the map)")
    sigma_noise_median_mm: float | None = Field(
        None, description="the same of its sensor-noise part, mm")
    sigma_model_median_mm: float | None = Field(
        None, description="the same of the calibration's part, mm")


PositiveMm = Annotated[float, Field(strict=True, gt=0.0, le=1000.0)]
BoardSize = Annotated[list[Annotated[int, Field(ge=2, le=200)]], Field(min_length=2, max_length=2)]
#: ``inner_corners`` is the grid size for every board type; an older ``grid`` key is read too
InnerCorners = Annotated[BoardSize, Field(validation_alias=AliasChoices("inner_corners", "grid"))]


class CheckerboardIn(Strict):
    """A checkerboard ``board.json``: inner corners [cols, rows] and square size, mm."""

    type: Literal["checkerboard"]
    inner_corners: InnerCorners
    square_mm: PositiveMm

    _integers = integers_are_numbers("inner_corners")


class CirclesIn(Strict):
    """A (symmetric or asymmetric) circle grid ``board.json``: grid [cols, rows] and spacing, mm."""

    type: Literal["circles", "asymmetric_circles"]
    inner_corners: InnerCorners
    spacing_mm: PositiveMm

    _integers = integers_are_numbers("inner_corners")


BoardIn = Annotated[CheckerboardIn | CirclesIn, Field(discriminator="type")]


class PoseOut(BaseModel):
    index: int
    found: bool
    corners: int
    created: str
    exposure_ms: float
    led: str
    preview_url: str


class PoseAdviceOut(BaseModel):
    """The next board pose (app.calib.coverage.PoseAdvice)."""

    region: str = Field(description="image region for the board's centre: 'lower-left', "
                                    "'upper', 'centre', ...")
    u_px: float = Field(description="that region's centre, column, px")
    v_px: float = Field(description="that region's centre, row, px")
    height_mm: float = Field(description="the board centre's height above the reference plane, mm")
    tilt_vertical_deg: float = Field(
        description="tilt about the image's vertical axis, deg (+: right edge nearer)")
    tilt_horizontal_deg: float = Field(
        description="tilt about the horizontal axis, deg (+: bottom edge nearer)")
    text: str = Field(description="the advice in words")


class CoverageOut(BaseModel):
    """Image x height cells the found poses cover, and the model's sigma per cell."""

    cells: list[int] = Field(description="[columns, rows] of image cells")
    height_edges_mm: list[float] = Field(
        description="height bin edges above the reference plane, mm")
    poses: int = Field(description="poses with the board found")
    covered: list[list[list[int]]] = Field(description="[bin][row][col] 1 where board points fall")
    sigma_model_um: list[list[list[float | None]]] = Field(
        description="[bin][row][col] the depth model's 1-sigma at the cell centre, um "
                    "(null: no model yet)")
    covered_share: float = Field(description="share of cells with board points")
    calibrated_share: float = Field(
        description="share of cells covered or with sigma_model within tolerance")
    target_share: float = Field(
        description="calibrated share at which the volume counts as reached")
    sigma_tolerance_um: float
    reached: bool = Field(description="the calibrated volume reaches the target")
    status: str = Field(description="the shares against the target, one line")
    suggestion: PoseAdviceOut


class SessionOut(BaseModel):
    board: dict[str, Any]
    created: str
    poses: list[PoseOut]
    solved: bool
    coverage: CoverageOut


class SolveIn(Strict):
    robust: StrictBool = False


class PoseReportOut(BaseModel):
    pose: int
    name: str
    corners: int
    reprojection_px: float | None
    rms_mm: float | None
    points: int
    dropped: bool
    height_mm: list[float | None]


class RefinementOut(BaseModel):
    """The joint (corners + phase) refinement's verdict: accepted only while its corner
    reprojection stays within the corners' noise of the corners-only fit (app.calib.refine)."""

    accepted: bool
    corners_rms_px: float | None = Field(description="corners-only fit's RMS reprojection, px")
    joint_rms_px: float | None = Field(description="joint fit's RMS reprojection, same corners, px")
    noise_px: float | None = Field(description="the corners' noise per coordinate, px")
    chi2: float | None = Field(description="the joint fit's squared distance from the corners-only "
                                           "fit, in the corners' covariance")
    chi2_limit: float | None = Field(description="chi-square quantile (99 %) it must not exceed")
    parameters: int = Field(description="camera and pose parameters of the corner fit")
    reason: str = Field(description="what was kept and why (rejected: the corners-only camera)")


class SolveOut(BaseModel):
    poses: list[PoseReportOut]
    rms_mm: float | None
    reprojection_px: float | None
    height_range_mm: list[float]
    table: str
    model: str = Field("eq5", description="the depth model the fit keeps: eq5 | geometric")
    held_out: dict[str, dict[str, float | int | str | None]] = Field(
        default_factory=dict,
        description="per model, leave-one-pose-out height errors (rms_mm, max_mm, points)")
    refinement: RefinementOut | None = Field(
        None, description="the joint (corners + phase) refinement's verdict; null when not tried")


class ActivateIn(Strict):
    name: str = Field("session", pattern=r"^[A-Za-z0-9_-]{1,64}$")


class RoiIn(Strict):
    roi: Annotated[list[Annotated[int, Field(ge=0, le=1_000_000)]],
                   Field(min_length=4, max_length=4)] = Field(
        ..., description="[x0, y0, x1, y1] pixels, x1/y1 exclusive. Rule (422 otherwise): "
                         "x0 < x1 and y0 < y1, and the box inside the depth map")

    _integers = integers_are_numbers("roi")

    @model_validator(mode="after")
    def _ordered(self) -> RoiIn:
        x0, y0, x1, y1 = self.roi
        if x1 <= x0 or y1 <= y0:
            raise ValueError(f"roi: need x0 < x1 and y0 < y1, got {list(self.roi)}")
        return self

    @property
    def box(self) -> tuple[int, int, int, int]:
        x0, y0, x1, y1 = self.roi
        return x0, y0, x1, y1


class FeatureIn(RoiIn):
    polarity: Literal["bright", "dark"] = "bright"


class PlaneOut(BaseModel):
    accuracy_mm: float | None
    precision_mm: float | None
    flatness_mm: float | None
    points: int
    extra: dict[str, Any] = {}


class FeatureOut(BaseModel):
    height_mm: float | None
    height_std_mm: float | None
    count: int
    extra: dict[str, Any] = {}


# -- recordings ------------------------------------------------------------------------------------
#: a recording's name: one plain path component (the folder under data/recordings)
RECORDING_NAME_REGEX = NAME_PATTERN.pattern


class RecordingStartIn(Strict):
    name: str | None = Field(None, pattern=RECORDING_NAME_REGEX, max_length=64,
                             description="folder name under data/recordings "
                                         "(default: rec_<UTC time>)")


class RecorderStatus(BaseModel):
    recording: str | None
    sets: int
    sets_with_depth: int
    skipped_sets: int
    errors: int
    last_error: str | None
    queue_peak: int = Field(0, description="most sets waiting for the writer at once")
    write_cpu_ms_per_set: float = Field(0.0, description="the writer's CPU time per set written "
                                        "(its encoder threads' included), ms")
    write_ms_per_set: float = Field(0.0, description="the writer's elapsed time per set written, "
                                    "ms (far above the CPU time: the machine is short of CPU)")


class RecordingSummary(BaseModel):
    name: str
    started: str | None
    stopped: str | None
    n_sets: int
    bytes: int
    interrupted: bool = Field(False, description="the service stopped without closing it; "
                              "stopped is then its last whole set's time")


class RecordingStopOut(BaseModel):
    recording: None = None
    stopped: dict[str, Any] | None = Field(None,
                                           description="session.json of the recording just stopped")


class RecordingDeletedOut(BaseModel):
    deleted: str


# -- limits ----------------------------------------------------------------------------------------
class LimitsOut(BaseModel):
    """The instrument's fixed ranges, for clients (the dashboard reads them from here)."""

    leds: list[str]
    exposure_ms: list[float] = Field(..., min_length=2, max_length=2,
                                     description="[min, max] camera exposure, ms")
    bit_depths: list[int] = Field(..., description="sensor bit depths the camera offers")
    depth_range_mm: list[float] = Field(..., min_length=2, max_length=2,
                                        description="default colormap [min, max], mm")


# -- measure --------------------------------------------------------------------------------------
Pixel = Annotated[list[Annotated[float, Field(strict=True, ge=-1e6, le=1e6)]],
                  Field(min_length=2, max_length=2)]
MEASURE_KINDS = Literal["length", "point_to_line", "depth", "profile", "area"]


class MeasureSpec(Strict):
    kind: MEASURE_KINDS = Field(..., description=(
        "length: 2 points; point_to_line: the point, then 2 on the line; depth: the point, "
        "then 3 spanning the plane (signed, + toward the scope); profile: a polyline of ≥ 2 "
        "points (heights against its chord, or against `reference`); area: a polygon of ≥ 3 "
        "points, on the surface (mm²)"))
    points: list[Pixel] = Field(..., min_length=2, max_length=256, description=(
        "[[u, v], …] image pixels (column, row). Rule (422 otherwise): as many as `kind` "
        "needs — length 2, point_to_line 3, depth 4, profile ≥ 2, area ≥ 3 — not collinear "
        "or coincident where a line or plane is spanned"))
    reference: list[Pixel] | None = Field(None, max_length=3,
                                          description="profile only: 3 pixels of a reference plane "
                                                      "(default: the chord)")
    snap_px: float = Field(3.0, strict=True, ge=0.0, le=20.0,
                           description="an invalid click snaps to the nearest valid pixel "
                                                             "within this radius, px")

    @model_validator(mode="before")
    @classmethod
    def _too_few_points(cls, data: Any) -> Any:
        """Fewer points than any kind takes (the schema's minItems): the reason names its count."""
        points = data.get("points") if isinstance(data, dict) else None
        kind = data.get("kind") if isinstance(data, dict) else None
        if isinstance(points, list) and len(points) < 2 and isinstance(kind, str) \
                and kind in MIN_POINTS:
            exact = EXACT_POINTS.get(kind)
            need = f"exactly {exact}" if exact is not None else f"at least {MIN_POINTS[kind]}"
            raise ValueError(f"{kind}: needs {need} points, got {len(points)}")
        return data


class MeasureIn(MeasureSpec):
    recording: str | None = Field(None, pattern=RECORDING_NAME_REGEX, max_length=64,
                                  description="measure on this recording's set (default: "
                                              "the latest live result)")
    index: int | None = Field(None, ge=0, le=999_999,
                              description="the recording's set index (with `recording`)")

    _integers = integers_are_numbers("index")

    @model_validator(mode="after")
    def _both(self) -> MeasureIn:
        if (self.recording is None) != (self.index is None):
            raise ValueError("recording and index: give both (a recorded set) or "
                             "neither (the live result)")
        return self


class PickedOut(BaseModel):
    requested: list[float]
    pixel: list[int]
    point_mm: list[float | None]
    sigma_mm: float | None
    snapped: bool
    snap_px: float
    filled: bool = Field(False, description="in a hole too wide to snap across: fitted from the "
                         "valid points around it")
    coverage: float = Field(1.0, description="valid share of the pixels the point rests on")


class ProfileOut(BaseModel):
    pixels: list[list[int]]
    distance_mm: list[float | None]
    height_mm: list[float | None]
    sigma_mm: list[float | None]


class MeasureOut(BaseModel):
    kind: str
    value_mm: float | None = Field(..., description="mm (area: mm²)")
    sigma_mm: float | None = Field(..., description="1-σ of value_mm, from the per-pixel σ")
    unit: str
    points: list[PickedOut]
    snapped: bool
    profile: ProfileOut | None = None
    extra: dict[str, Any] = {}
    source: dict[str, Any] = {}
    coverage: float = Field(1.0, description="valid share of the pixels measured (area: the "
                            "polygon's; profile: the samples; length: its least covered point)")
    min_coverage: float = Field(0.5, description="below this coverage a measurement is refused "
                                "(422)")
    elapsed_ms: float


class MeasureToolIn(Strict):
    measurements: list[MeasureSpec] = Field(..., max_length=32,
                                            description="kept and re-measured on "
                                                        "every recorded depth map")


class MeasureToolOut(BaseModel):
    measurements: list[MeasureSpec]


# -- request bodies FastAPI does not build from a model -----------------------------------------
_NUMBERS = {"type": "array", "items": {"type": "number"}}
#: ``PUT /api/calibration/file``: the keys and shapes every calibration file has; the values
#: themselves are checked by the server (physical sense, fit to this camera and pattern)
CALIBRATION_FILE_SCHEMA: dict[str, Any] = {
    "type": "object",
    "description": "a calibration file as GET /api/calibration/file gives it",
    "required": ["format", "image_size", "camera_matrix", "dist_coeffs", "reference_plane", "model",
                 "pattern"],
    "properties": {
        "format": {"type": "string", "enum": [CALIBRATION_FORMAT, CALIBRATION_FORMAT_V1]},
        "image_size": {"type": "array", "items": {"type": "integer", "minimum": 1},
                       "minItems": 2, "maxItems": 2, "description": "[width, height], px"},
        "camera_matrix": {"type": "array", "items": {**_NUMBERS, "minItems": 3, "maxItems": 3},
                          "minItems": 3, "maxItems": 3},
        "dist_coeffs": {**_NUMBERS, "minItems": 1, "maxItems": 14},
        "reference_plane": {"type": "object", "required": ["normal", "offset_mm"], "properties": {
            "normal": {**_NUMBERS, "minItems": 3, "maxItems": 3}, "offset_mm": {"type": "number"}}},
        "model": {"type": "object"},
        "pattern": {"type": "object", "required": ["frequencies", "steps", "width"]},
    },
}
CALIBRATION_UPLOAD: dict[str, Any] = {"requestBody": {"required": True, "description": (
    "Rule (422 otherwise): a whole calibration file whose values make physical sense and fit "
    "this camera and pattern schedule"), "content": {
    "application/json": {"schema": CALIBRATION_FILE_SCHEMA}}}}

#: ``POST /api/reconstruct`` and ``/api/phase``: a capture set as its files, or one .zip
CAPTURE_UPLOAD: dict[str, Any] = {"requestBody": {"required": True, "description": (
    "Rule (422 otherwise): a whole capture set — capture.json and every frame it lists (PNG or "
    "TIFF, the calibration's size; without one at most 4096 × 4096 pixels a frame and 256 MiB "
    "decoded a set) — as multipart files or one .zip"), "content": {
    "multipart/form-data": {"schema": {"type": "object", "required": ["files"], "properties": {
        "files": {"type": "array", "minItems": 1, "maxItems": 200,
                  "items": {"type": "string", "format": "binary"}}}}},
    "application/zip": {"schema": {"type": "string", "format": "binary"}},
}}}
