"""Errors → HTTP, in one place, and the OpenAPI ``responses`` every route declares.

Domain errors (:mod:`app.core.errors`) carry their reason to the client: InvalidRequest
422, Conflict 409, NotFound 404, DeviceUnavailable 503 (as do device errors: the
hardware failed); a nearly full disk when recording is 507. Request validation is 422
with pydantic's detail. Anything else is a programming error: 500 with a generic
reason, its traceback logged.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.routing import Match, Mount

from app.core.errors import Conflict, DeviceUnavailable, DomainError, InvalidRequest, NotFound
from app.devices.errors import DeviceError
from app.service.recorder import InsufficientDisk

log = logging.getLogger("fringescope.api")

METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "TRACE")

STATUS: dict[type[DomainError], int] = {
    InvalidRequest: 422, Conflict: 409, NotFound: 404, DeviceUnavailable: 503,
}


def status_of(exc: DomainError) -> int:
    for cls in type(exc).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


MAX_ECHO_CHARS = 80  # an input echoed back in an error is cut to this (it may be huge)


def _echo(value: Any, depth: int = 0) -> Any:
    """``value`` as plain JSON: non-finite floats and bytes as text, long strings cut."""
    if isinstance(value, bool) or value is None or isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, str):
        return value if len(value) <= MAX_ECHO_CHARS else value[:MAX_ECHO_CHARS] + "…"
    if isinstance(value, dict) and depth < 4:
        return {_echo(str(k)): _echo(v, depth + 1) for k, v in list(value.items())[:16]}
    if isinstance(value, list | tuple) and depth < 4:
        return [_echo(v, depth + 1) for v in list(value)[:16]]
    return _echo(repr(value)) if not isinstance(value, dict | list | tuple) else "…"


def field_path(loc: Sequence[Any]) -> str:
    """A pydantic ``loc`` as one name: ``("body", "points", 0, 1)`` → ``body.points[0][1]``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            text = str(part)
            if len(text) > 40 or not text.isprintable():
                text = repr(text[:40]) + f"…({len(text)} chars)" if len(text) > 40 else repr(text)
            out += ("." if out else "") + text
    return out or "request"


def validation_detail(errors: Sequence[Any]) -> tuple[str, list[dict[str, Any]]]:
    """(one line naming each refused field, pydantic's errors made serialisable)."""
    items = []
    for err in errors:
        loc = [p if isinstance(p, int) else _echo(str(p)) for p in err.get("loc", ())]
        items.append({"loc": loc,
                      "msg": str(err.get("msg", "")), "type": str(err.get("type", "")),
                      **({"input": _echo(err["input"])} if "input" in err else {})})
    lines = [f"{field_path(err.get('loc', ()))}: {err.get('msg', 'invalid')}" for err in errors]
    line = "; ".join(lines[:5]) + (f"; and {len(lines) - 5} more" if len(lines) > 5 else "")
    return " ".join(line.split()) or "invalid request", items


def install_error_handlers(app: FastAPI) -> None:
    """Register the one mapping of exceptions to HTTP answers on ``app``."""

    async def domain(_: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, DomainError)
        return JSONResponse({"detail": exc.detail}, status_code=status_of(exc))

    async def invalid(_: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        detail, items = validation_detail(exc.errors())
        return JSONResponse({"detail": detail, "errors": items}, status_code=422)

    async def device(_: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(exc) or type(exc).__name__}, status_code=503)

    async def disk(_: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": f"cannot record: {exc}"}, status_code=507)

    async def internal(request: Request, exc: Exception) -> JSONResponse:
        log.error("%s %s failed", request.method, request.url.path, exc_info=exc)
        detail = f"internal error ({type(exc).__name__}); see the server log"
        return JSONResponse({"detail": detail}, status_code=500)

    app.add_exception_handler(RequestValidationError, invalid)
    app.add_exception_handler(DomainError, domain)
    app.add_exception_handler(DeviceError, device)
    app.add_exception_handler(InsufficientDisk, disk)
    app.add_exception_handler(Exception, internal)


async def _api_fallback(request: Request) -> JSONResponse:
    """404 for an unknown ``/api`` path, 405 listing the allowed methods for a known one.

    Module-level and reading the routes from ``request.app``: an endpoint defined inside
    :func:`install_api_fallback` would hold its app, and FastAPI's endpoint caches would then
    keep every app (and its Instrument) a process ever built.
    """
    path = request.url.path
    allowed = set()
    for method in METHODS:
        scope = {**request.scope, "method": method}
        for route in request.app.router.routes:
            if isinstance(route, Mount) or getattr(route, "endpoint", None) is _api_fallback:
                continue
            if route.matches(scope)[0] is Match.FULL:
                allowed.add(method)
                break
    if not allowed:
        return JSONResponse({"detail": f"no such API route: {path}"}, status_code=404)
    allow = ", ".join(sorted(allowed - {"HEAD"}))
    return JSONResponse({"detail": f"{request.method} not allowed on {path} (allowed: {allow})"},
                        status_code=405, headers={"Allow": allow})


def install_api_fallback(app: FastAPI) -> None:
    """Unknown ``/api`` paths are 404 and wrong methods 405 listing every allowed method.

    Without it the dashboard mounted at ``/`` would answer them (405 ``Allow: GET, HEAD``).
    Call after every API route is included and before the dashboard is mounted.
    """
    app.add_api_route("/api/{rest:path}", _api_fallback, include_in_schema=False,
                      methods=list(METHODS))


# -- OpenAPI: the answers a route can give besides its 200 -----------------------------------------
_DETAIL: dict[str, Any] = {"type": "string", "description": "what is wrong, one line"}
_VALIDATION_ITEM: dict[str, Any] = {"type": "object", "required": ["loc", "msg", "type"],
                                    "properties": {
    "loc": {"type": "array", "items": {"anyOf": [{"type": "string"}, {"type": "integer"}]}},
    "msg": {"type": "string"}, "type": {"type": "string"}}}


Responses = dict[int | str, dict[str, Any]]


def _err(description: str, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    properties = {"detail": _DETAIL, **(extra or {})}
    schema = {"type": "object", "required": ["detail"], "properties": properties}
    return {"description": description, "content": {"application/json": {"schema": schema}}}


R400: Responses = {400: _err("malformed request body (e.g. a broken multipart form)")}
R404: Responses = {404: _err("no such thing (reason in detail)")}
R409: Responses = {409: _err("not possible in the current state (reason in detail)")}
R413: Responses = {413: _err("request body larger than the route's limit (upload limit, "
                              "or kilobytes for a JSON body)")}
R415: Responses = {415: _err("unsupported upload content type")}
#: request validation or a domain InvalidRequest: one line naming the field(s) and why; for
#: request validation also pydantic's errors (loc, msg, type, the input cut short)
R422: Responses = {422: _err("invalid request: one line naming each refused field and why",
                             {"errors": {"type": "array", "items": _VALIDATION_ITEM}})}
R503: Responses = {503: _err("device or live pipeline unavailable now (reason in detail)")}
R507: Responses = {507: _err("not enough free disk space")}

#: every route needs the instrument: 503 when it is not available
COMMON: Responses = {**R503}
