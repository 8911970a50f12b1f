"""Shared route helpers: the Instrument (and Recorder) from the app, binary responses."""

from __future__ import annotations

from typing import Any

from fastapi import Request
from fastapi.responses import Response

from app.core.errors import DeviceUnavailable
from app.service.instrument import Instrument
from app.service.recorder import Recorder


def get_instrument(request: Request) -> Instrument:
    inst = getattr(request.app.state, "instrument", None)
    if inst is None:
        raise DeviceUnavailable("instrument not started")
    return inst  # type: ignore[no-any-return]


def get_recorder(request: Request) -> Recorder:
    rec = getattr(request.app.state, "recorder", None)
    if rec is None:
        raise DeviceUnavailable("recorder not available")
    return rec  # type: ignore[no-any-return]


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
