"""Request bodies bounded per route and checked before any route parses them.

A JSON route needs kilobytes: its body is refused (413) as soon as ``Content-Length`` or the
bytes actually streamed pass the route's limit — nothing more is read, so a 10 MB body costs
the server nothing and other clients do not wait. A body within the limit is then checked
before the route sees it: nesting deeper than :data:`MAX_JSON_DEPTH` levels (measured by a
byte scan, never by recursion) and non-finite numbers (``NaN``, ``Infinity``, ``1e400``) are
422 naming where they are (``body.points[0][1]: NaN is not a finite number …``). Capture-set
uploads keep the upload limit (``max_upload_mb``) and their own checks (:mod:`app.api.upload`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from fastapi import FastAPI
from starlette.middleware import Middleware

from app.api.errors import R413, R422
from app.core.jsonlimits import MAX_JSON_DEPTH, loads_finite

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: the body limit of every JSON route not listed in :data:`JSON_LIMITS_BYTES`
DEFAULT_JSON_LIMIT_BYTES = 64 * 1024
#: routes whose JSON bodies may be larger: (method, path) → bytes
JSON_LIMITS_BYTES: dict[tuple[str, str], int] = {
    # a calibration file is ~60 kB (model coefficients, held-out figures, pose residuals)
    ("PUT", "/api/calibration/file"): 1024 * 1024,
    # 32 kept measurements of up to 256 points each
    ("PUT", "/api/measure/tool"): 1024 * 1024,
}
#: capture-set uploads: bounded by ``max_upload_mb`` and checked by app.api.upload
UPLOAD_ROUTES = frozenset({("POST", "/api/reconstruct"), ("POST", "/api/phase")})


def json_limit_bytes(method: str, path: str) -> int:
    """The body limit of JSON route ``method path`` (its path template), bytes."""
    return JSON_LIMITS_BYTES.get((method, path), DEFAULT_JSON_LIMIT_BYTES)


def json_routes(schema: dict[str, Any]) -> list[tuple[str, re.Pattern[str], int, bool]]:
    """(method, path pattern, body limit, also takes other bodies) of every operation of an
    OpenAPI document that takes a JSON body (the document is the one list of routes every
    FastAPI version gives). A route that also takes an upload (``POST /api/reference``) is
    checked only when the request's body is JSON."""
    out = []
    for path, item in schema.get("paths", {}).items():
        pattern = re.compile("^" + re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(path)) + "$")
        for method, op in item.items():
            content = op.get("requestBody", {}).get("content", {}) if isinstance(op, dict) else {}
            if "application/json" in content and (method.upper(), path) not in UPLOAD_ROUTES:
                mixed = len(content) > 1
                out.append((method.upper(), pattern, json_limit_bytes(method.upper(), path), mixed))
    return out


class BodyLimitMiddleware:
    """Pure ASGI middleware: per-route body size, JSON depth and finite numbers (see module).

    Only requests to a route that takes a JSON body are checked; any other request (an
    upload, a wrong method, an unknown path) passes untouched to the app, which answers it
    without reading a JSON body.
    """

    def __init__(self, app: ASGIApp, routes_of: FastAPI) -> None:
        self.app = app
        self.routes_of = routes_of
        self._routes: list[tuple[str, re.Pattern[str], int, bool]] | None = None

    def limit(self, method: str, path: str, content_type: str = "application/json"
              ) -> tuple[int, str] | None:
        """(body limit in bytes, route) for a request, or None when it is not a JSON route
        (or a route that also takes uploads, given one)."""
        if self._routes is None:  # the routes are all included by the first request
            self._routes = json_routes(self.routes_of.openapi())
        for route_method, pattern, limit, mixed in self._routes:
            if route_method == method and pattern.match(path):
                if mixed and content_type and "json" not in content_type:
                    return None  # an upload: the route's own limit and checks
                return limit, f"{method} {path}"
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v for k, v in scope.get("headers", [])}
        content_type = headers.get("content-type", b"").decode("latin-1").lower()
        found = self.limit(scope.get("method", "GET"), scope.get("path", ""), content_type)
        if found is None or (
            "content-length" not in headers and "transfer-encoding" not in headers
        ):
            await self.app(scope, receive, send)
            return
        limit, where = found
        declared = headers.get("content-length", b"").strip()
        if declared:
            if not declared.isdigit():
                await _answer(send, 400, "body: invalid Content-Length header")
                return
            if int(declared) > limit:
                await _answer(
                    send,
                    413,
                    f"body: {int(declared)} bytes exceed the {limit}-byte limit of {where}",
                )
                return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client left: nothing to answer
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:  # streamed (chunked) or more than announced: stop reading now
                await _answer(send, 413, f"body: more than {limit} bytes, the limit of {where}")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body.strip():
            reason = _json_fault(body)
            if reason is not None:
                await _answer(send, 422, reason)
                return
        await self.app(scope, _replay(body, receive), send)


def _json_fault(body: bytes) -> str | None:
    """Why ``body`` is refused before parsing (too deep, non-finite), or None.

    Text that is not JSON at all is left to the route (its own 422 or 415).
    """
    try:
        loads_finite(body, "body", MAX_JSON_DEPTH)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    except (ValueError, RecursionError) as exc:
        return str(exc)
    return None


def _replay(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that hands the app the body already read, then the client's own events."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def _answer(send: Send, status: int, detail: str) -> None:
    data = json.dumps({"detail": detail}).encode("utf-8")
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(data)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": data})


def install_body_limits(app: FastAPI) -> None:
    """Add the middleware innermost and state each route's limits in the OpenAPI document.

    Call after :func:`app.api.security.install_security`: the token and CORS middleware stay
    outside (a refusal carries CORS headers; no body is read before the token is checked),
    and this wraps the OpenAPI document that one builds.
    """
    if app.middleware_stack is not None:
        raise RuntimeError("install_body_limits: the app has already started")
    app.user_middleware.append(Middleware(BodyLimitMiddleware, routes_of=app))  # last = innermost
    previous = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = previous()
            document_body_limits(schema)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def document_body_limits(schema: dict[str, Any]) -> None:
    """Add each JSON route's body limit and its 413/422 answers to an OpenAPI document."""
    for path, item in schema.get("paths", {}).items():
        for method, op in item.items():
            if not isinstance(op, dict):
                continue
            answers = op.get("responses", {})
            if "422" in answers and "HTTPValidationError" in json.dumps(answers["422"]):
                answers["422"] = R422[422]  # FastAPI's default: a list; ours is one line
            if "requestBody" not in op:
                continue
            responses = op.setdefault("responses", {})
            responses.setdefault("413", R413[413])
            responses["422"] = R422[422]
            if "application/json" in op["requestBody"].get("content", {}):
                limit = json_limit_bytes(method.upper(), path)
                op["description"] = (
                    op.get("description", "") + f"\n\nBody: JSON, at most {limit} "
                    f"bytes, nested at most {MAX_JSON_DEPTH} levels, numbers finite."
                )
    for name in ("HTTPValidationError", "ValidationError"):
        if name not in json.dumps(schema.get("paths", {})):
            schema.get("components", {}).get("schemas", {}).pop(name, None)
