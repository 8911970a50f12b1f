"""The change reference (``/api/reference``) and the live change map (``/api/change/latest``)."""

from __future__ import annotations

import json
from typing import Any, Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from pydantic import BaseModel, Field, ValidationError
from starlette.concurrency import run_in_threadpool

from app.api.deps import binary, get_instrument
from app.api.errors import COMMON, R400, R404, R409, R413, R415, R422
from app.api.schemas import CAPTURE_UPLOAD, Strict, integers_are_numbers
from app.api.upload import capture_from_request, read_body
from app.capture.recording import recordings_root, validate_name
from app.core.errors import InvalidRequest
from app.outputs import encoding
from app.outputs.change import check_change_range, delta_color_png, delta_png
from app.service.instrument import Instrument

router = APIRouter(prefix="/api", tags=["change"])

_JSON_LIMIT_BYTES = 4096


class ReferenceRequest(Strict):
    """Which map becomes the reference: the newest (no body, or ``{}``) or a recorded set."""

    recording: str | None = Field(None, min_length=1, max_length=200,
                                  description="a recording's name (with index)")
    index: int | None = Field(None, ge=0, le=10**7, description="the set's index in it")

    _integers = integers_are_numbers("index")


class ReferenceInfo(BaseModel):
    created: str = Field(description="when the reference was taken (ISO 8601)")
    source: dict[str, Any] = Field(description="live (seq), recording (name, index) or upload")
    valid_share: float = Field(description="share of pixels with a depth")
    image_size: list[int] = Field(description="[width, height] px")
    calibration: str = Field(description="the creation time of the calibration it was taken with")


class ChangeSummary(BaseModel):
    seq: int = Field(description="the depth map's sequence number")
    created: str
    mode: Literal["fixed", "registered", "failed"]
    compared_pixels: int
    changed_pixels: int
    changed_share: float
    changed_area_mm2: float
    rise_mm: float | None
    rise_sigma_mm: float | None
    rise_px: list[int] | None = Field(description="[v, u] of the largest significant rise")
    sink_mm: float | None
    sink_sigma_mm: float | None
    sink_px: list[int] | None
    false_alarm_rate: float = Field(description="false-alarm rate of the mask per map: the "
                                    "probability that a still map shows any changed pixel")
    registration: dict[str, Any] | None = Field(
        description="ok, note, residual_mm, overlap, rotation_deg, translation_mm, transform "
                    "(4×4, current → reference camera frame), elapsed_ms; null: fixed scope")
    elapsed_ms: float


_UPLOAD = {"requestBody": {"required": False, "description": (
    "No body or {}: the newest depth map. JSON {\"recording\": NAME, \"index\": i}: that "
    "recorded set. Or an uploaded capture set (multipart files or one .zip, as "
    "POST /api/reconstruct). Rule (422 otherwise): recording and index together, a valid "
    "recording name; an upload is a whole capture set for the calibration."), "content": {
    "application/json": {"schema": ReferenceRequest.model_json_schema()},
    **CAPTURE_UPLOAD["requestBody"]["content"]}}}


@router.post("/reference", response_model=ReferenceInfo,
             responses={**R400, **R404, **R409, **R413, **R415, **R422, **COMMON},
             openapi_extra=_UPLOAD)
async def set_reference(request: Request,
                        inst: Instrument = Depends(get_instrument)) -> dict[str, Any]:
    """Take a reference for the change map (kept in the data folder, survives a restart)."""
    ctype = request.headers.get("content-type", "")
    if ctype.startswith(("multipart/form-data", "application/zip", "application/x-zip",
                         "application/octet-stream")):
        cal = inst.calibration
        capture = await capture_from_request(
            request, int(inst.settings.max_upload_mb * 1024 * 1024),
            frame_size=None if cal is None else cal.image_size)
        ref = await run_in_threadpool(inst.change.reference_from_capture, capture,
                                      inst.calibrations.reconstruct, {"kind": "upload"})
        return ref.describe()
    body = await read_body(request, _JSON_LIMIT_BYTES)
    try:  # the body-limit middleware has refused deep nesting and non-finite numbers
        doc = json.loads(body) if body.strip() else {}
    except ValueError as exc:
        raise InvalidRequest(f"body: not JSON ({str(exc).splitlines()[0]})") from None
    try:
        req = ReferenceRequest.model_validate(doc)
    except ValidationError as exc:  # one line naming the field, as every JSON route
        raise RequestValidationError(
            [{**e, "loc": ("body", *e["loc"])} for e in exc.errors()]) from None
    if (req.recording is None) != (req.index is None):
        raise InvalidRequest("body: give both recording and index, or neither")
    if req.recording is not None and req.index is not None:
        try:
            name = validate_name(req.recording, "recording")
        except ValueError as exc:
            raise InvalidRequest(str(exc)) from None
        ref = await run_in_threadpool(inst.change.reference_from_recording,
                                      recordings_root(inst.settings.data_dir), name, req.index,
                                      inst.calibrations.reconstruct)
        return ref.describe()
    res = inst.latest_result()
    ref = inst.change.set_reference(res.depth, res.sigma_noise, res.points,
                                    {"kind": "live", "seq": res.seq}, res.sigma_model)
    return ref.describe()


@router.get("/reference", response_model=ReferenceInfo, responses={**R404, **COMMON})
def get_reference(inst: Instrument = Depends(get_instrument)) -> dict[str, Any]:
    """The reference: when, from where, its valid share."""
    return inst.change.reference().describe()


@router.delete("/reference", status_code=204, responses={**R404, **COMMON})
def delete_reference(inst: Instrument = Depends(get_instrument)) -> Response:
    """Clear the reference (the change map stops)."""
    inst.change.clear_reference()
    return Response(status_code=204)


@router.get("/change/summary", response_model=ChangeSummary,
            responses={**R404, **R409, **COMMON})
def change_summary(inst: Instrument = Depends(get_instrument)) -> dict[str, Any]:
    """The newest change map's figures: changed area, largest rise and sink ± σ, registration."""
    change = inst.change.latest()
    return {"seq": change.seq, "created": change.created, **change.summary}


@router.get(
    "/change/latest",
    responses={200: {"content": {"application/octet-stream": {}, "image/png": {}}},
               **R404, **R409, **R422, **COMMON},
)
def change_latest(
    format: Literal["npy", "png", "color"] = "npy",
    field: Literal["delta", "sigma", "significance", "changed"] = Query(
        "delta", description="delta Δ (mm, + toward the scope), sigma σ_Δ (mm), significance "
                             "|Δ|/σ_Δ, changed (bool mask). Rule (422 otherwise): "
                             "field=changed with format=npy only"),
    range_mm: float = Query(1.0, gt=0, le=100, allow_inf_nan=False,
                            description="png/color of delta: colours span ±range_mm"),
    inst: Instrument = Depends(get_instrument),
) -> Response:
    """The newest change map: ``npy`` float32 (NaN not compared), ``png`` diverging colours
    with a bar in mm and the changed contour, ``color`` the same without the bar."""
    change = inst.change.latest()
    cm = change.result.cmap
    headers = {"X-Fringescope-Seq": change.seq, "X-Fringescope-Change-Mode": change.result.mode}
    if field == "changed":
        if format != "npy":
            raise InvalidRequest("format: field=changed is a mask, served as npy only")
        return binary(change.cached("changed", lambda: encoding.npy_bytes(cm.changed)),
                      "application/octet-stream", headers, "changed.npy")
    if format == "npy":
        arrays = {"delta": lambda: cm.delta, "sigma": lambda: cm.sigma,
                  "significance": lambda: cm.significance}
        data = change.cached((field, "npy"), lambda: encoding.npy_bytes(arrays[field]()))
        return binary(data, "application/octet-stream", headers, f"{field}.npy")
    if field == "delta":
        r = check_change_range(range_mm)
        make = delta_png if format == "png" else delta_color_png
        data = change.cached((field, format, r), lambda: make(cm.delta, cm.changed, r))
        return binary(data, "image/png", headers, f"delta_{format}.png")
    top = 0.2 if field == "sigma" else 10.0  # σ_Δ in mm; significance in σ_Δ
    data = change.cached((field, format), lambda: encoding.depth_color_png(
        cm.sigma if field == "sigma" else cm.significance, (0.0, top)))
    return binary(data, "image/png", headers, f"{field}.png")
