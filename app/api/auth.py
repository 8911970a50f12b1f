"""Sign-in for browsers and the health check.

A browser page cannot put a header on ``<img>``, a WebSocket or the viewer's iframe, so the
dashboard sends the token once to ``POST /api/login`` (bearer header), which opens a session
and sets its id — random, never the token — as an ``HttpOnly; SameSite=Strict`` cookie
(``Secure`` over HTTPS) accepted for reads and streams. The security middleware
(:mod:`app.api.security`) has already checked the token when the route runs.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from pydantic import BaseModel

from app.api.security import TOKEN_COOKIE, guard_of, session_cookie, session_id

router = APIRouter(tags=["auth"])


class AuthState(BaseModel):
    token_required: bool
    authenticated: bool


class Health(BaseModel):
    status: str


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """Liveness only (open; nothing patient-related): the process answers HTTP."""
    return Health(status="ok")


@router.get("/api/auth", response_model=AuthState)
def auth_state(request: Request) -> AuthState:
    """Whether this server wants a token, and whether this request carries it (open)."""
    guard = guard_of(request.app)
    return AuthState(token_required=guard.token is not None,
                     authenticated=guard.authenticated(request.scope))


@router.post("/api/login", response_model=AuthState, responses={
    401: {"description": "missing or invalid token"},
    429: {"description": "too many wrong tokens from this client: retry later"}})
def login(request: Request, response: Response) -> AuthState:
    """Exchange the bearer token for a session cookie (``HttpOnly; SameSite=Strict``; the
    session ends after ``session_ttl_s``, at logout, or when the token changes)."""
    guard = guard_of(request.app)
    token = guard.token
    if token is not None:  # the middleware let this POST through only with the right token
        sid = guard.sessions.open(token)
        response.headers.append("set-cookie",
                                session_cookie(sid, secure=guard.over_https(request.scope)))
    return AuthState(token_required=token is not None, authenticated=True)


@router.post("/api/logout", response_model=AuthState)
def logout(request: Request, response: Response) -> AuthState:
    """End this browser's session and forget its cookie (open)."""
    guard = guard_of(request.app)
    sid = session_id(request.scope)
    if sid is not None:
        guard.sessions.revoke(sid)
    response.delete_cookie(TOKEN_COOKIE, path="/", httponly=True, samesite="strict",
                           secure=guard.over_https(request.scope))
    return AuthState(token_required=guard.token is not None, authenticated=guard.token is None)
