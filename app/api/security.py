"""Network hardening: bearer token, startup refusal, CORS, WebSocket Origin, upload limit.

Rules (issue 7):

- Loopback by default. On any other address a token (``FRINGESCOPE_API_TOKEN``) is
  required, and :func:`check_startup_security` refuses to start without one unless
  ``insecure`` is set (``--insecure`` / ``FRINGESCOPE_INSECURE=1``).
- When a token is configured (on any address; off loopback one is required) it guards
  every route that returns or changes data (issue 16): everything under ``/api`` (depth,
  points, texture, reasons, results, status, recordings and their files, calibrations,
  streams incl. WebSockets and MJPEG), the viewer relay ``/viser`` (HTTP and WebSocket) and
  every WebSocket. Open without a token: ``/healthz`` (liveness only, nothing
  patient-related), ``GET /api/auth`` (is a token needed, is this request authenticated),
  ``POST /api/logout``, the dashboard's static files (no data in them) and the API
  description (``/docs``, ``/redoc``, ``/openapi.json``).
- How to pass the token: ``Authorization: Bearer <token>`` always. Browsers cannot set
  headers on ``<img>``, a WebSocket or an iframe, so reads (GET/HEAD) and WebSockets also
  accept the cookie ``fringescope_token`` — ``HttpOnly; SameSite=Strict``, set by
  ``POST /api/login`` (bearer header) — and the viewer relay and WebSockets the query
  ``?token=<token>`` (after a valid query token the response sets that cookie). Cookies and
  queries are never accepted for state-changing requests (no cross-site request forgery);
  a query token may end up in proxy logs, prefer the cookie.
- CORS is closed unless ``cors_origins`` lists origins. A WebSocket whose ``Origin``
  is neither the server's own host nor a listed origin is refused (HTTP 403).
- Request bodies above ``max_upload_mb`` get 413 with a reason, whether announced by
  ``Content-Length`` or streamed (chunked).
"""

from __future__ import annotations

import hmac
import json
import re
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlsplit

from fastapi import FastAPI, HTTPException
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi

from app.capture.recording import validate_name
from app.config import Settings, is_loopback

TOKEN_COOKIE = "fringescope_token"
TOKEN_QUERY = "token"
STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
PROTECTED_PREFIXES = ("/api", "/viser")  # everything here needs the token when one is set
VIEWER_PREFIXES = ("/viser",)  # also accepts ?token= (an iframe cannot send a header)
OPEN_PATHS = frozenset({"/healthz", "/api/auth", "/api/logout"})  # no data in them
SAFE_METHODS = frozenset({"GET", "HEAD"})
_TOKEN_PATTERN = re.compile(r'[!#-+\--:<-\[\]-~]{1,512}')  # cookie-safe: no space " , ; \\

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def check_startup_security(settings: Settings) -> None:
    """Raise ``ValueError`` if ``settings`` would expose the service without a token."""
    token = settings.api_token
    if token is not None and not _TOKEN_PATTERN.fullmatch(token):
        raise ValueError(
            "api_token: FRINGESCOPE_API_TOKEN must be 1-512 printable ASCII characters "
            "without spaces, quotes, commas, semicolons or backslashes"
        )
    if not is_loopback(settings.host) and not settings.api_token and not settings.insecure:
        raise ValueError(
            f"refusing to listen on {settings.host} without FRINGESCOPE_API_TOKEN "
            "(use --insecure to override)"
        )


def checked_name(name: str, what: str = "name") -> str:
    """:func:`validate_name` for routes: a bad name is HTTP 400 with the reason."""
    try:
        return validate_name(name, what)
    except ValueError as exc:
        raise HTTPException(status_code=400, detail=str(exc)) from None


def _headers(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}


def supplied_tokens(scope: Scope, *, allow_cookie: bool, allow_query: bool | None = None) -> list[str]:
    """Tokens a request carries: the bearer header, plus cookie and query if allowed.

    ``allow_query`` defaults to ``allow_cookie``.
    """
    if allow_query is None:
        allow_query = allow_cookie
    headers = _headers(scope)
    found: list[str] = []
    scheme, _, value = headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        found.append(value.strip())
    if allow_cookie:
        cookie = SimpleCookie()
        try:
            cookie.load(headers.get("cookie", ""))
        except Exception:  # a malformed cookie header is just no token
            cookie = SimpleCookie()
        if TOKEN_COOKIE in cookie:
            found.append(cookie[TOKEN_COOKIE].value)
    if allow_query:
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        found.extend(query.get(TOKEN_QUERY, [])[:1])
    return found


def _under(path: str, prefixes: tuple[str, ...]) -> bool:
    return any(path == p or path.startswith(p + "/") for p in prefixes)


def token_rule(scope: Scope) -> tuple[bool, bool, bool]:
    """(needs the token, cookie accepted, query accepted) for a request when a token is set."""
    path = scope.get("path", "")
    viewer = _under(path, VIEWER_PREFIXES)
    if scope["type"] == "websocket":
        return True, True, True
    method = scope.get("method", "GET")
    if path in OPEN_PATHS:
        return False, False, False
    if method in STATE_CHANGING:
        return True, False, False
    needs = _under(path, PROTECTED_PREFIXES)
    safe = method in SAFE_METHODS
    return needs, needs and safe, needs and safe and viewer


def request_authenticated(scope: Scope, token: str | None) -> bool:
    """True if no token is configured or the request carries it (header or cookie)."""
    if not token:
        return True
    return token_matches(token, supplied_tokens(scope, allow_cookie=True, allow_query=False))


def token_matches(expected: str, supplied: list[str]) -> bool:
    """Constant-time comparison of each supplied token with the expected one."""
    want = expected.encode("utf-8")
    ok = False
    for tok in supplied:
        ok |= hmac.compare_digest(want, tok.encode("utf-8", "surrogateescape"))
    return ok


def origin_allowed(scope: Scope, allowed_origins: list[str]) -> bool:
    """A WebSocket ``Origin`` is fine if absent (not a browser), same host, or listed."""
    headers = _headers(scope)
    origin = headers.get("origin")
    if origin is None:
        return True
    if origin in allowed_origins or "*" in allowed_origins:
        return True
    host = headers.get("host", "")
    try:
        netloc = urlsplit(origin).netloc
    except ValueError:
        return False
    return bool(host) and netloc.lower() == host.lower()


def token_cookie(token: str, *, secure: bool) -> str:
    """``Set-Cookie`` value carrying the token for this browser session (no expiry)."""
    return f"{TOKEN_COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict" + ("; Secure" if secure else "")


class UploadTooLarge(HTTPException):
    def __init__(self, size: int, limit: int) -> None:
        super().__init__(
            status_code=413,
            detail=f"request body too large: {size / 1e6:.1f} MB exceeds the limit of "
                   f"{limit / 1e6:.1f} MB (FRINGESCOPE_MAX_UPLOAD_MB)",
        )


class SecurityMiddleware:
    """Pure ASGI middleware enforcing the token, WebSocket Origin and upload-size rules."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.token = settings.api_token or None
        self.allowed_origins = list(settings.cors_origins)
        self.max_body = int(settings.max_upload_mb * 1_000_000)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind == "websocket":
            await self._websocket(scope, receive, send)
        elif kind == "http":
            await self._http(scope, receive, send)
        else:
            await self.app(scope, receive, send)

    async def _websocket(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not origin_allowed(scope, self.allowed_origins):
            await send({"type": "websocket.close", "code": 1008, "reason": "origin not allowed"})
            return
        needs, cookie, query = token_rule(scope)
        if needs and self.token and not token_matches(
                self.token, supplied_tokens(scope, allow_cookie=cookie, allow_query=query)):
            await send({"type": "websocket.close", "code": 1008, "reason": "missing or invalid token"})
            return
        await self.app(scope, receive, send)

    async def _http(self, scope: Scope, receive: Receive, send: Send) -> None:
        needs, cookie, query = token_rule(scope)
        set_cookie = False
        if needs and self.token:
            if not token_matches(self.token, supplied_tokens(scope, allow_cookie=cookie, allow_query=query)):
                await _json(send, 401, "missing or invalid token: send 'Authorization: Bearer "
                            "<FRINGESCOPE_API_TOKEN>'", {"www-authenticate": "Bearer"})
                return
            params = parse_qs(scope.get("query_string", b"").decode("latin-1"))
            set_cookie = query and bool(params.get(TOKEN_QUERY))
        length = _headers(scope).get("content-length")
        if length is not None:
            try:
                announced = int(length)
            except ValueError:
                await _json(send, 400, "invalid Content-Length header")
                return
            if announced > self.max_body:
                await _json(send, 413, UploadTooLarge(announced, self.max_body).detail)
                return
        received = 0
        started = False

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body:
                    raise UploadTooLarge(received, self.max_body)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                if set_cookie and self.token:
                    value = token_cookie(self.token, secure=scope.get("scheme") == "https")
                    message = {**message, "headers": [*message.get("headers", []),
                                                      (b"set-cookie", value.encode("latin-1"))]}
            await send(message)

        try:
            await self.app(scope, counting_receive, tracking_send)
        except UploadTooLarge as exc:  # the app let it through (e.g. a raw body read)
            if started:
                raise
            await _json(send, 413, str(exc.detail))


async def _json(send: Send, status: int, detail: str, extra: dict[str, str] | None = None) -> None:
    body = json.dumps({"detail": detail}).encode("utf-8")
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.encode("latin-1"), v.encode("latin-1")) for k, v in (extra or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


def install_security(app: FastAPI, settings: Settings) -> None:
    """Check the startup rule and add the security (and, if configured, CORS) middleware.

    Call once in ``create_app`` before the app serves. Also documents the bearer
    scheme in the OpenAPI spec so ``/docs`` offers an *Authorize* button.
    """
    check_startup_security(settings)
    app.add_middleware(SecurityMiddleware, settings=settings)
    if settings.cors_origins:  # added last = outermost, so 401/413 answers carry CORS headers
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.cors_origins),
            allow_methods=["GET", "POST", "PUT", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
        )
    if settings.api_token:
        _document_bearer(app)


def _document_bearer(app: FastAPI) -> None:
    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, routes=app.routes,
                                 description=app.description)
            schema.setdefault("components", {}).setdefault("securitySchemes", {})["bearer"] = {
                "type": "http", "scheme": "bearer",
                "description": "FRINGESCOPE_API_TOKEN; required for every route under /api "
                               "except /api/auth and /api/logout (the cookie set by "
                               "POST /api/login also works for GET)",
            }
            for path, item in schema.get("paths", {}).items():
                for method, op in item.items():
                    scope = {"type": "http", "path": path, "method": method.upper()}
                    if isinstance(op, dict) and token_rule(scope)[0]:
                        op.setdefault("security", [{"bearer": []}])
                        op.setdefault("responses", {}).setdefault(
                            "401", {"description": "missing or invalid token"})
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
