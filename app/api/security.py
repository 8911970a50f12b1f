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
  accept the session cookie ``fringescope_token`` — ``HttpOnly; SameSite=Strict``, plus
  ``Secure`` when the request came over HTTPS (directly, or by ``X-Forwarded-Proto`` from a
  proxy listed in ``trusted_proxies``), set by ``POST /api/login`` (bearer header) — and the
  viewer relay and WebSockets the query ``?token=<token>`` (after a valid query token the
  response sets that cookie). The cookie is a random session id, never the token
  (:mod:`app.api.sessions`): it expires after ``session_ttl_s``, dies at logout and when the
  token changes. Cookies and queries are never accepted for state-changing requests (no
  cross-site request forgery); a query token may end up in proxy logs, prefer the cookie.
- The token has at least :data:`MIN_TOKEN_CHARS` characters (refused at start-up). After
  a few wrong tokens a client is held off (429 with ``Retry-After``, doubling up to a minute)
  before its next attempt is even compared.
- Every answer carries ``X-Content-Type-Options: nosniff``, ``X-Frame-Options: SAMEORIGIN``
  (the dashboard frames the viewer) and ``Referrer-Policy: no-referrer``; the dashboard's
  files also a ``Content-Security-Policy`` allowing only this origin.
- CORS is closed unless ``cors_origins`` lists origins. A WebSocket whose ``Origin``
  is neither the server's own host nor a listed origin is refused (HTTP 403).
- Request bodies above ``max_upload_mb`` get 413 with a reason, whether announced by
  ``Content-Length`` or streamed (chunked).
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import math
import re
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any, NamedTuple
from urllib.parse import parse_qs, urlsplit

from fastapi import FastAPI, HTTPException
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi

from app.api.sessions import FailureThrottle, SessionStore
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
#: shortest token accepted at start-up (a guessable token protects nothing)
MIN_TOKEN_CHARS = 12
#: on every answer; the dashboard frames the viewer relay, so frames from this origin only
COMMON_HEADERS = ((b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"SAMEORIGIN"),
                  (b"referrer-policy", b"no-referrer"))
#: the dashboard's pages: scripts, styles, images, streams and frames from this origin only
#: (``blob:`` / ``data:`` images: the page shows fetched PNGs as object URLs)
DASHBOARD_CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; "
                 "img-src 'self' blob: data:; connect-src 'self'; frame-src 'self'; "
                 "frame-ancestors 'self'; object-src 'none'; base-uri 'self'; form-action 'self'")
#: paths that are not the dashboard (the API documentation loads its own scripts)
NOT_DASHBOARD = ("/api", "/viser", "/docs", "/redoc", "/openapi.json", "/healthz")

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def check_startup_security(settings: Settings) -> None:
    """Raise ``ValueError`` (one line) if ``settings`` would expose the service without a
    token, or with a token too short or not cookie-safe."""
    token = settings.api_token
    if token is not None and not _TOKEN_PATTERN.fullmatch(token):
        raise ValueError(
            "api_token: FRINGESCOPE_API_TOKEN must be 1-512 printable ASCII characters "
            "without spaces, quotes, commas, semicolons or backslashes"
        )
    if token is not None and len(token) < MIN_TOKEN_CHARS:
        raise ValueError(
            f"api_token: FRINGESCOPE_API_TOKEN must have at least {MIN_TOKEN_CHARS} characters, "
            f"got {len(token)}"
        )
    for proxy in settings.trusted_proxies:
        if not _is_ip(proxy):
            raise ValueError(f"trusted_proxies: {proxy!r} is not an IP address")
    if not is_loopback(settings.host) and not settings.api_token and not settings.insecure:
        raise ValueError(
            f"refusing to listen on {settings.host} without FRINGESCOPE_API_TOKEN "
            "(use --insecure to override)"
        )


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def checked_name(name: str, what: str = "name") -> str:
    """:func:`validate_name` for routes: a bad name is HTTP 400 with the reason."""
    try:
        return validate_name(name, what)
    except ValueError as exc:
        raise HTTPException(status_code=400, detail=str(exc)) from None


def _headers(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}


def supplied_tokens(scope: Scope, *, allow_query: bool) -> list[str]:
    """Tokens a request carries: the bearer header, plus the ``?token=`` query if allowed."""
    headers = _headers(scope)
    found: list[str] = []
    scheme, _, value = headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        found.append(value.strip())
    if allow_query:
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        found.extend(query.get(TOKEN_QUERY, [])[:1])
    return found


def session_id(scope: Scope) -> str | None:
    """The session cookie's value, if the request carries one."""
    cookie: SimpleCookie = SimpleCookie()
    try:
        cookie.load(_headers(scope).get("cookie", ""))
    except Exception:  # a malformed cookie header is just no session
        return None
    return cookie[TOKEN_COOKIE].value if TOKEN_COOKIE in cookie else None


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


def session_cookie(session: str, *, secure: bool) -> str:
    """``Set-Cookie`` value carrying a session id (a browser-session cookie: no expiry date;
    the server forgets the session after ``session_ttl_s``)."""
    return (f"{TOKEN_COOKIE}={session}; Path=/; HttpOnly; SameSite=Strict"
            + ("; Secure" if secure else ""))


class Verdict(NamedTuple):
    """The token check of one request: passed, or refused (and for how long held off)."""

    ok: bool
    retry_after_s: float = 0.0


class Guard:
    """The token rules of one app: the configured token, its sessions, the failure throttle.

    The token is read from ``settings`` at every request: replacing it closes every session.
    """

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.sessions = SessionStore(settings.session_ttl_s)
        self.throttle = FailureThrottle()
        self._trusted = frozenset(ipaddress.ip_address(p) for p in settings.trusted_proxies)

    @property
    def token(self) -> str | None:
        return self.settings.api_token or None

    def _from_trusted_proxy(self, scope: Scope) -> bool:
        peer = (scope.get("client") or ("", 0))[0]
        try:
            return ipaddress.ip_address(peer) in self._trusted
        except ValueError:
            return False

    def client_address(self, scope: Scope) -> str:
        """The client's address: the peer's, or the one a trusted proxy forwarded."""
        peer = str((scope.get("client") or ("unknown", 0))[0])
        if self._from_trusted_proxy(scope):
            forwarded = _headers(scope).get("x-forwarded-for", "")
            hops = [h.strip() for h in forwarded.split(",") if h.strip()]
            if hops:
                return hops[-1]  # the address the proxy itself saw
        return peer

    def over_https(self, scope: Scope) -> bool:
        """True if the request reached us over TLS, or a trusted proxy says it reached it so."""
        if scope.get("scheme") in ("https", "wss"):
            return True
        if not self._from_trusted_proxy(scope):
            return False
        proto = _headers(scope).get("x-forwarded-proto", "").split(",")[0].strip().lower()
        return proto in ("https", "wss")

    def check(self, scope: Scope, *, allow_cookie: bool, allow_query: bool) -> Verdict:
        """Whether the request carries the token (or a live session when cookies count).

        A token that is sent is an attempt: a held-off client's is not compared at all, a
        wrong one counts against the client, a right one clears its count.
        """
        token = self.token
        if token is None:
            return Verdict(True)
        tokens = supplied_tokens(scope, allow_query=allow_query)
        if tokens:
            client = self.client_address(scope)
            wait_s = self.throttle.held_off_s(client)
            if wait_s > 0:
                return Verdict(False, wait_s)
            if token_matches(token, tokens):
                self.throttle.succeeded(client)
                return Verdict(True)
            self.throttle.failed(client)
            return Verdict(False)
        sid = session_id(scope) if allow_cookie else None
        return Verdict(sid is not None and self.sessions.valid(sid, token))

    def authenticated(self, scope: Scope) -> bool:
        """True if no token is configured or the request carries it (header or session)."""
        return self.check(scope, allow_cookie=True, allow_query=False).ok


def guard_of(app: Any) -> Guard:
    """The :class:`Guard` :func:`install_security` put on ``app.state``."""
    guard = getattr(app.state, "guard", None)
    if not isinstance(guard, Guard):
        raise RuntimeError("install_security was not called on this app")
    return guard


class UploadTooLarge(HTTPException):
    def __init__(self, size: int, limit: int) -> None:
        super().__init__(
            status_code=413,
            detail=f"request body too large: {size / 1e6:.1f} MB exceeds the limit of "
                   f"{limit / 1e6:.1f} MB (FRINGESCOPE_MAX_UPLOAD_MB)",
        )


HELD_OFF = "too many wrong tokens from this client: retry in {:.0f} s"


class SecurityMiddleware:
    """Pure ASGI middleware enforcing the token, WebSocket Origin and upload-size rules, and
    adding the security headers."""

    def __init__(self, app: ASGIApp, settings: Settings, guard: Guard) -> None:
        self.app = app
        self.guard = guard
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
        if needs:
            verdict = self.guard.check(scope, allow_cookie=cookie, allow_query=query)
            if not verdict.ok:
                reason = (HELD_OFF.format(math.ceil(verdict.retry_after_s)) if verdict.retry_after_s
                          else "missing or invalid token")
                await send({"type": "websocket.close", "code": 1008, "reason": reason})
                return
        await self.app(scope, receive, send)

    async def _http(self, scope: Scope, receive: Receive, send: Send) -> None:
        needs, cookie, query = token_rule(scope)
        set_cookie = False
        guard = self.guard
        if needs and guard.token:
            verdict = guard.check(scope, allow_cookie=cookie, allow_query=query)
            if verdict.retry_after_s > 0:
                wait = math.ceil(verdict.retry_after_s)
                await _json(send, 429, HELD_OFF.format(wait), {"retry-after": str(wait)})
                return
            if not verdict.ok:
                await _json(send, 401, "missing or invalid token: send 'Authorization: Bearer "
                            "<FRINGESCOPE_API_TOKEN>'", {"www-authenticate": "Bearer"})
                return
            set_cookie = bool(query and supplied_tokens(scope, allow_query=True)
                              != supplied_tokens(scope, allow_query=False))
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
        dashboard = not _under(scope.get("path", ""), NOT_DASHBOARD)

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
                headers = [*message.get("headers", []), *COMMON_HEADERS]
                if dashboard:
                    headers.append((b"content-security-policy", DASHBOARD_CSP.encode()))
                token = guard.token
                if set_cookie and token:
                    value = session_cookie(guard.sessions.open(token),
                                           secure=guard.over_https(scope))
                    headers.append((b"set-cookie", value.encode("latin-1")))
                message = {**message, "headers": headers}
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
    headers += COMMON_HEADERS
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


def install_security(app: FastAPI, settings: Settings) -> None:
    """Check the startup rule and add the security (and, if configured, CORS) middleware.

    Call once in ``create_app`` before the app serves. The :class:`Guard` (token, sessions,
    throttle) is ``app.state.guard``. Also documents the bearer scheme in the OpenAPI spec so
    ``/docs`` offers an *Authorize* button.
    """
    check_startup_security(settings)
    guard = Guard(settings)
    app.state.guard = guard
    app.add_middleware(SecurityMiddleware, settings=settings, guard=guard)
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
                        responses = op.setdefault("responses", {})
                        responses.setdefault("401", {"description": "missing or invalid token"})
                        responses.setdefault("429", {"description": "too many wrong tokens from "
                                                                    "this client: retry later"})
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
