"""Recording routes: start/stop, list, metadata, zip download, delete, per-set depth export."""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter, Body, HTTPException, Request
from fastapi import Path as PathParam
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from app.capture import recording as rec_io
from app.service.recorder import Recorder, RecorderBusy

router = APIRouter(prefix="/api", tags=["recording"])

NAME_REGEX = rec_io.NAME_PATTERN.pattern
Name = PathParam(..., pattern=NAME_REGEX, max_length=64, description="recording name")


class RecordingStartIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str | None = Field(None, pattern=NAME_REGEX, max_length=64,
                             description="folder name under data/recordings (default: rec_<UTC time>)")


class RecorderStatus(BaseModel):
    recording: str | None
    sets: int
    sets_with_depth: int
    skipped_sets: int
    errors: int
    last_error: str | None


class RecordingSummary(BaseModel):
    name: str
    started: str | None
    stopped: str | None
    n_sets: int
    bytes: int


class RecordingStopOut(BaseModel):
    recording: None = None
    stopped: dict[str, Any] | None = Field(None, description="session.json of the recording just stopped")


def get_recorder(request: Request) -> Recorder:
    rec = getattr(request.app.state, "recorder", None)
    if rec is None:
        raise HTTPException(503, "recorder not available")
    return rec  # type: ignore[no-any-return]


def _root(request: Request) -> Any:
    return get_recorder(request).root


@router.get("/recording", response_model=RecorderStatus)
def recording_status(request: Request) -> dict[str, Any]:
    """Is a recording running, how many sets it holds, its last error."""
    return get_recorder(request).status()


@router.post("/recording/start", response_model=RecorderStatus,
             responses={409: {"description": "already recording, or the name exists"},
                        507: {"description": "not enough free disk space"}})
def recording_start(
    request: Request,
    body: RecordingStartIn = Body(default_factory=RecordingStartIn),
) -> dict[str, Any]:
    """Record every whole fringe set (PNG frames) with its depth map until stopped."""
    recorder = get_recorder(request)
    try:
        return recorder.start(body.name)
    except (RecorderBusy, FileExistsError) as exc:
        raise HTTPException(409, str(exc)) from None
    except ValueError as exc:
        raise HTTPException(400, str(exc)) from None
    except OSError as exc:
        raise HTTPException(507, f"cannot record: {exc}") from None


@router.post("/recording/stop", response_model=RecordingStopOut)
def recording_stop(request: Request) -> dict[str, Any]:
    """Finish the running recording (idempotent: ``stopped`` is null if none was running)."""
    return {"recording": None, "stopped": get_recorder(request).stop()}


@router.get("/recordings", response_model=list[RecordingSummary])
def recordings_list(request: Request) -> list[dict[str, Any]]:
    """Every recording in the data folder, by name."""
    return rec_io.list_recordings(_root(request))


def _not_found(exc: FileNotFoundError) -> HTTPException:
    return HTTPException(404, str(exc).strip("'\""))


@router.get("/recordings/{name}.zip", responses={200: {"content": {"application/zip": {}}}, 404: {}})
def recording_zip(request: Request, name: str = Name) -> StreamingResponse:
    """The whole recording as one zip, streamed (session.json + set folders)."""
    try:
        chunks = rec_io.iter_zip(_root(request), name)
    except FileNotFoundError as exc:
        raise _not_found(exc) from None
    return StreamingResponse(chunks, media_type="application/zip", headers={
        "Content-Disposition": f'attachment; filename="{name}.zip"', "Cache-Control": "no-store"})


@router.get("/recordings/{name}", responses={404: {}})
def recording_meta(request: Request, name: str = Name) -> dict[str, Any]:
    """``session.json`` of a recording (start, stop, settings, sets with time stamps)."""
    try:
        return rec_io.read_session(_root(request), name)
    except FileNotFoundError as exc:
        raise _not_found(exc) from None


@router.delete("/recordings/{name}", responses={404: {}, 409: {}})
def recording_delete(request: Request, name: str = Name) -> dict[str, str]:
    """Delete a recording (not the one being written)."""
    if get_recorder(request).active_name == name:
        raise HTTPException(409, f"recording {name!r} is running: stop it first")
    try:
        rec_io.delete_recording(_root(request), name)
    except FileNotFoundError as exc:
        raise _not_found(exc) from None
    return {"deleted": name}


@router.get("/recordings/{name}/sets/{index}/depth",
            responses={200: {"content": {"application/octet-stream": {}, "image/tiff": {}}}, 404: {}})
def recording_set_depth(
    request: Request, name: str = Name, index: int = PathParam(..., ge=0, le=999_999),
    format: Literal["npy", "tiff"] = "npy",
) -> Response:
    """One recorded depth map, mm: ``npy`` float32 or ``tiff`` 32-bit float (NaN invalid)."""
    import numpy as np

    try:
        session = rec_io.read_session(_root(request), name)
    except FileNotFoundError as exc:
        raise _not_found(exc) from None
    folder = f"set_{index:04d}"
    if not any(s["folder"] == folder for s in session["sets"]):
        raise HTTPException(404, f"recording {name!r} has no set {index}")
    path = rec_io.safe_child(_root(request), name) / folder / "depth.npy"
    if not path.is_file():
        raise HTTPException(404, f"set {index} of {name!r} was recorded without a depth map")
    depth = np.load(path, allow_pickle=False)
    if format == "tiff":
        data, media, fname = rec_io.depth_tiff_bytes(depth), "image/tiff", f"{name}_{folder}_depth.tiff"
    else:
        data, media, fname = rec_io.depth_npy_bytes(depth), "application/octet-stream", f"{name}_{folder}_depth.npy"
    return Response(data, media_type=media, headers={
        "Content-Disposition": f'attachment; filename="{fname}"', "Cache-Control": "no-store"})
