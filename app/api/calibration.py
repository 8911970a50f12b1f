"""The calibration workflow: session with a board, poses, solve, activate; file up/download."""

from __future__ import annotations

import json
import math
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from app.api.deps import CalibrationsDep, InstrumentDep, SettingsDep, binary
from app.api.errors import COMMON, R400, R404, R409, R413, R422, Responses
from app.api.schemas import (
    CALIBRATION_UPLOAD,
    ActivateIn,
    BoardIn,
    CalibrationSummary,
    CoverageOut,
    PoseAdviceOut,
    PoseOut,
    SessionOut,
    SolveIn,
    SolveOut,
)
from app.api.upload import read_body
from app.core.calibration import Calibration
from app.core.errors import InvalidRequest, NotFound

router = APIRouter(prefix="/api/calibration", tags=["calibration"])

#: skip the dry run on the newest frames (never the physical checks)
Force = Annotated[bool, Query(description="activate even if the dry run on the newest "
                                          "frames leaves far fewer valid pixels than "
                                          "the active calibration")]
JSON_TYPES = ("application/json",)

# OpenAPI links (followed by clients and by the stateful schemathesis run)
_INDEX_LINK = {"parameters": {"index": "$response.body#/index"}}
POSE_LINKS: Responses = {200: {"description": "Successful Response", "links": {
    "PosePreview": {"operationId": "pose_preview", **_INDEX_LINK},
    "PoseDelete": {"operationId": "delete_pose", **_INDEX_LINK},
}}}
SESSION_LINKS: Responses = {200: {"description": "Successful Response", "links": {
    "Session": {"operationId": "get_session"}, "Poses": {"operationId": "list_poses"},
    "CapturePose": {"operationId": "capture_pose"},
}}}


def _num(x: Any) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None


@router.get("", response_model=CalibrationSummary, responses={**R404, **COMMON})
def active(calibrations: CalibrationsDep) -> Any:
    """The active calibration (404 if there is none)."""
    summary = calibrations.summary()
    if summary is None:
        raise NotFound("no calibration is active")
    return summary.to_dict()


@router.post("/session", response_model=SessionOut,
             responses={**SESSION_LINKS, **R400, **R422, **COMMON})
def new_session(board: BoardIn, calibrations: CalibrationsDep) -> Any:
    """Start a session with a board spec (``board.json`` format); replaces any previous one."""
    return calibrations.start_session(board.model_dump()).describe()


@router.get("/session", response_model=SessionOut, operation_id="get_session",
            responses={**R409, **COMMON})
def get_session(calibrations: CalibrationsDep) -> Any:
    """The open session: its board, poses and whether it is solved (409 if none is open)."""
    return calibrations.require_session().describe()


class PoseSuggestionOut(BaseModel):
    index: int = Field(description="the pose to capture next (0: the reference plane)")
    of: int = Field(description="poses in the suggested series")
    height_mm: float = Field(description="the board centre's height above the reference plane")
    tilt_deg: float = Field(description="the board's tilt from the reference plane")
    moved: bool = Field(description="the simulator moved its board there (false on hardware)")
    exposure_ms: float | None = Field(description="the exposure set for the twin's board (or null)")
    hint: str = Field(description="where to hold the board, one line")
    suggestion: PoseAdviceOut
    coverage: CoverageOut


@router.post("/session/suggested-pose", response_model=PoseSuggestionOut,
             operation_id="suggest_pose", responses={**R409, **COMMON})
def suggest_pose(inst: InstrumentDep) -> Any:
    """Where to hold the board next; on the simulator its board is moved there (a few seconds)."""
    return inst.wizard.suggest_pose()


class SessionCancelOut(BaseModel):
    cancelled: bool = Field(description="a session was open and is now closed")
    poses: int = Field(description="poses the cancelled session held (0 if none was open)")


@router.delete("/session", response_model=SessionCancelOut, operation_id="cancel_session",
               responses=COMMON)
def cancel_session(inst: InstrumentDep) -> SessionCancelOut:
    """Close the session without a calibration (its poses are dropped); none open: nothing to do."""
    session = inst.wizard.cancel_session()
    poses = 0 if session is None else len(session.poses)
    return SessionCancelOut(cancelled=session is not None, poses=poses)


@router.post("/session/poses", operation_id="capture_pose",
             responses={**POSE_LINKS, **R409, **COMMON})
def capture_pose(calibrations: CalibrationsDep) -> dict[str, Any]:
    """Capture the current view as a pose: {index, found, corners, preview_url, corner_points,
    coverage} (coverage: the cells covered so far, sigma_model per cell, the next pose)."""
    return calibrations.capture_pose(15.0)


@router.get("/session/poses", response_model=list[PoseOut], operation_id="list_poses",
            responses={**R409, **COMMON})
def list_poses(calibrations: CalibrationsDep) -> Any:
    return calibrations.require_session().summaries()


@router.get("/session/poses/{index}/preview.png", operation_id="pose_preview",
            responses={200: {"content": {"image/png": {}}}, **R404, **R409, **R422, **COMMON})
def pose_preview(index: int, calibrations: CalibrationsDep) -> Response:
    """The pose's texture with the detected board points drawn."""
    return binary(calibrations.require_session().pose(index).preview_png, "image/png", None,
                  f"pose_{index:02d}.png")


@router.delete("/session/poses/{index}", response_model=list[PoseOut], operation_id="delete_pose",
               responses={**R404, **R409, **R422, **COMMON})
def delete_pose(index: int, calibrations: CalibrationsDep) -> Any:
    """Remove a pose; later poses move down one index."""
    session = calibrations.require_session()
    session.delete(index)
    return session.summaries()


@router.post("/session/solve", response_model=SolveOut,
             responses={**R409, **R400, **R422, **COMMON})
def solve(
    calibrations: CalibrationsDep,
    body: SolveIn = Body(default_factory=SolveIn),
) -> Any:
    """Fit the calibration from the detected poses: per-pose table and totals."""
    report = calibrations.solve_session(robust=body.robust)
    return {
        "poses": [
            {"pose": p.pose, "name": p.name, "corners": p.corners,
             "reprojection_px": _num(p.reprojection_px), "rms_mm": _num(p.rms_mm),
             "points": p.points, "dropped": p.dropped, "height_mm": [_num(h) for h in p.height_mm]}
            for p in report.poses
        ],
        "rms_mm": _num(report.rms_mm),
        "reprojection_px": _num(report.reprojection_px),
        "height_range_mm": list(report.calibration.height_range_mm),
        "table": report.table(),
        "model": report.calibration.model.name,
        "held_out": report.held_out,
        "refinement": None if report.refinement is None else report.refinement.to_dict(),
    }


@router.post("/session/activate", response_model=CalibrationSummary,
             responses={**R409, **R400, **R422, **COMMON})
def activate(
    inst: InstrumentDep,
    body: ActivateIn = Body(default_factory=ActivateIn),
    force: Force = False,
) -> Any:
    """Check the solved calibration (physical checks, then a dry run on the newest frames unless
    ``force``; 422 naming the reason), then make it active and save it in the data folder."""
    return inst.wizard.activate_session(body.name, force=force)


@router.get("/file", responses={200: {"content": {"application/json": {}}}, **R404, **COMMON})
def download(calibrations: CalibrationsDep) -> Response:
    """The active calibration file (``fringescope.calibration/1`` JSON)."""
    cal = calibrations.calibration
    if cal is None:
        raise NotFound("no calibration is active")
    data = (json.dumps(cal.to_dict(), indent=2) + "\n").encode()
    name = calibrations.name or "calibration"
    return binary(data, "application/json", None, f"{name}.json")


@router.put(
    "/file",
    response_model=CalibrationSummary,
    responses={**R413, **R422, **COMMON},
    openapi_extra=CALIBRATION_UPLOAD,
)
async def upload(request: Request, calibrations: CalibrationsDep, settings: SettingsDep,
                 force: Force = False) -> Any:
    """Upload a calibration file (JSON body, ``Content-Type: application/json``).

    It goes live only after the physical checks and a dry run on the newest frames (skipped
    with ``force``) pass; otherwise 422 naming the reason, and nothing changes.
    """
    from starlette.concurrency import run_in_threadpool

    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in JSON_TYPES and not media.endswith("+json"):
        raise InvalidRequest("calibration: Content-Type must be application/json, "
                             f"got {media or 'none'!r}")
    body = await read_body(request, int(settings.max_upload_mb * 1024 * 1024))
    try:
        data = json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InvalidRequest(f"calibration: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise InvalidRequest("calibration: expected a JSON object")
    try:  # the file is the user's input: whatever does not fit it is their error
        cal = Calibration.from_dict(data)
        await run_in_threadpool(calibrations.activate, cal, name="uploaded", persist=True,
                                force=force)
    except (ValueError, KeyError, TypeError) as exc:
        raise InvalidRequest(f"calibration: {exc}") from None
    summary = calibrations.summary()
    return None if summary is None else summary.to_dict()
