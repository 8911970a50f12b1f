"""Shared route helpers: the app's parts as ``Annotated`` dependencies, binary responses.

Routers name the part they use (``PipelineDep``, ``CalibrationsDep``, ``RecorderDep``) and
call it directly; ``InstrumentDep`` is for what cuts across parts (schedule and control
changes, the status record, the calibration wizard's steps on the live view:
``instrument.wizard``).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.responses import Response

from app.config import Settings
from app.core.errors import DeviceUnavailable
from app.service.alarms import AlarmBoard
from app.service.calibrations import CalibrationManager
from app.service.instrument import Instrument
from app.service.pipeline import LivePipeline
from app.service.recorder import Recorder


def get_instrument(request: Request) -> Instrument:
    inst = getattr(request.app.state, "instrument", None)
    if inst is None:
        raise DeviceUnavailable("instrument not started")
    return inst  # type: ignore[no-any-return]


async def get_instrument_now(request: Request) -> Instrument:
    """The instrument, on the event loop: a plain (sync) dependency costs a worker-thread hop,
    which under load (streams, busy cores) waits for a thread and for the GIL twice."""
    return get_instrument(request)


def get_recorder(request: Request) -> Recorder:
    rec = getattr(request.app.state, "recorder", None)
    if rec is None:
        raise DeviceUnavailable("recorder not available")
    return rec  # type: ignore[no-any-return]


def get_alarms(request: Request) -> AlarmBoard:
    """The alarms shown until acknowledged."""
    return get_instrument(request).alarms


def get_pipeline(request: Request) -> LivePipeline:
    """The live pipeline (devices, acquisition, reconstruction, the latest result)."""
    return get_instrument(request).pipeline


def get_calibrations(request: Request) -> CalibrationManager:
    """The calibration manager (the active calibration, uploads, the wizard's session)."""
    return get_instrument(request).calibrations


def get_settings(request: Request) -> Settings:
    """The settings the instrument was built from."""
    return get_instrument(request).settings


InstrumentDep = Annotated[Instrument, Depends(get_instrument)]
InstrumentNowDep = Annotated[Instrument, Depends(get_instrument_now)]
PipelineDep = Annotated[LivePipeline, Depends(get_pipeline)]
CalibrationsDep = Annotated[CalibrationManager, Depends(get_calibrations)]
RecorderDep = Annotated[Recorder, Depends(get_recorder)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
AlarmsDep = Annotated[AlarmBoard, Depends(get_alarms)]


def binary(data: bytes, media_type: str, headers: dict[str, Any] | None = None,
           filename: str | None = None) -> Response:
    h = {k: str(v) for k, v in (headers or {}).items()}
    if filename:
        h["Content-Disposition"] = f'inline; filename="{filename}"'
    h["Cache-Control"] = "no-store"
    return Response(content=data, media_type=media_type, headers=h)


def result_headers(meta: dict[str, Any]) -> dict[str, Any]:
    return {
        "X-Fringescope-Seq": meta["seq"],
        "X-Fringescope-Mode": meta["mode"],
        "X-Fringescope-Exposure-Ms": meta["exposure_ms"],
        "X-Fringescope-Led": meta["led"],
        "X-Fringescope-Latency-Ms": meta["latency_ms"],
    }
