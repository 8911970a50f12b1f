"""Recording routes: start/stop, list, metadata, zip download, delete, per-set depth export."""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter, Body
from fastapi import Path as PathParam
from fastapi.responses import Response, StreamingResponse
from starlette.convertors import StringConvertor, register_url_convertor

from app.api.deps import RecorderDep, binary
from app.api.errors import COMMON, R400, R404, R409, R422, R507, Responses
from app.api.schemas import (
    RECORDING_NAME_REGEX,
    RecorderStatus,
    RecordingDeletedOut,
    RecordingStartIn,
    RecordingStopOut,
    RecordingSummary,
)
from app.capture.recording import depth_npy_bytes, depth_tiff_bytes

router = APIRouter(prefix="/api", tags=["recording"])


class _RecordingName(StringConvertor):
    """A recording name in a route path; never ``*.zip``, which is the download route's path."""

    regex = r"[^/]+(?<!\.zip)"


register_url_convertor("recording", _RecordingName())

Name = PathParam(..., pattern=RECORDING_NAME_REGEX, max_length=64, description="recording name")


@router.get("/recording", response_model=RecorderStatus, responses=COMMON)
def recording_status(recorder: RecorderDep) -> dict[str, Any]:
    """Is a recording running, how many sets it holds, its last error."""
    return recorder.status()


_NAME_LINK = {"parameters": {"name": "$response.body#/recording"}}
START_LINKS: Responses = {200: {"description": "Successful Response", "links": {
    "RecordingMeta": {"operationId": "recording_meta", **_NAME_LINK},
    "RecordingZip": {"operationId": "recording_zip", **_NAME_LINK},
    "RecordingDelete": {"operationId": "recording_delete", **_NAME_LINK},
}}}


@router.post("/recording/start", response_model=RecorderStatus,
             responses={**START_LINKS, **R409, **R400, **R422, **R507, **COMMON})
def recording_start(
    recorder: RecorderDep,
    body: RecordingStartIn = Body(default_factory=RecordingStartIn),
) -> dict[str, Any]:
    """Record every whole fringe set (zstd frames, see README) with its depth map until stopped."""
    return recorder.start(body.name)


@router.post("/recording/stop", response_model=RecordingStopOut, responses=COMMON)
def recording_stop(recorder: RecorderDep) -> dict[str, Any]:
    """Finish the running recording (idempotent: ``stopped`` is null if none was running)."""
    return {"recording": None, "stopped": recorder.stop()}


@router.get("/recordings", response_model=list[RecordingSummary], responses=COMMON)
def recordings_list(recorder: RecorderDep) -> list[dict[str, Any]]:
    """Every recording in the data folder, by name (``interrupted``: not closed by the service)."""
    return recorder.recordings()


@router.get("/recordings/{name}.zip", operation_id="recording_zip",
            responses={200: {"content": {"application/zip": {}}}, **R404, **R422, **COMMON})
def recording_zip(recorder: RecorderDep, name: str = Name) -> StreamingResponse:
    """The whole recording as one zip, streamed (session.json + set folders)."""
    return StreamingResponse(recorder.zip_chunks(name), media_type="application/zip", headers={
        "Content-Disposition": f'attachment; filename="{name}.zip"', "Cache-Control": "no-store"})


@router.get("/recordings/{name:recording}", operation_id="recording_meta",
            responses={**R404, **R422, **COMMON})
def recording_meta(recorder: RecorderDep, name: str = Name) -> dict[str, Any]:
    """``session.json`` of a recording (start, stop, settings, sets with time stamps)."""
    return recorder.session(name)


@router.delete("/recordings/{name:recording}", response_model=RecordingDeletedOut,
               operation_id="recording_delete", responses={**R404, **R409, **R422, **COMMON})
def recording_delete(recorder: RecorderDep, name: str = Name) -> RecordingDeletedOut:
    """Delete a recording (not the one being written)."""
    recorder.delete(name)
    return RecordingDeletedOut(deleted=name)


@router.get("/recordings/{name}/sets/{index}/depth",
            responses={200: {"content": {"application/octet-stream": {}, "image/tiff": {}}},
                       **R404, **R422, **COMMON})
def recording_set_depth(
    recorder: RecorderDep, name: str = Name, index: int = PathParam(..., ge=0, le=999_999),
    format: Literal["npy", "tiff"] = "npy",
) -> Response:
    """One recorded depth map, mm: ``npy`` float32 or ``tiff`` 32-bit float (NaN invalid)."""
    depth = recorder.set_depth(name, index)
    stem = f"{name}_set_{index:04d}_depth"
    if format == "tiff":
        return binary(depth_tiff_bytes(depth), "image/tiff", None, f"{stem}.tiff")
    return binary(depth_npy_bytes(depth), "application/octet-stream", None, f"{stem}.npy")
