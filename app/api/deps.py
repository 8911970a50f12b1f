"""Shared route helpers: the Instrument from the app, error mapping, binary responses."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import JSONResponse, Response

from app.devices.errors import DeviceError
from app.service.instrument import Instrument, NotReady


def get_instrument(request: Request) -> Instrument:
    inst = getattr(request.app.state, "instrument", None)
    if inst is None:
        raise HTTPException(503, "instrument not started")
    return inst  # type: ignore[no-any-return]


def install_error_handlers(app: FastAPI) -> None:
    """Service exceptions → HTTP: NotReady 503, ValueError 422, IndexError 404, DeviceError 503."""

    async def not_ready(_: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    async def invalid(_: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=422)

    async def missing(_: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(exc).strip("'\"")}, status_code=404)

    app.add_exception_handler(NotReady, not_ready)
    app.add_exception_handler(DeviceError, not_ready)
    app.add_exception_handler(ValueError, invalid)
    app.add_exception_handler(IndexError, missing)


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
