"""Sign-in for browsers and the health check (issue 16).

A browser page cannot put a header on ``<img>``, a WebSocket or the viewer's iframe, so the
dashboard sends the token once to ``POST /api/login`` (bearer header), which sets an
``HttpOnly; SameSite=Strict`` session cookie accepted for reads and streams. The security
middleware (:mod:`app.api.security`) has already checked the token when the route runs.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from pydantic import BaseModel

from app.api.security import TOKEN_COOKIE, request_authenticated, token_cookie

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
    token = request.app.state.settings.api_token
    return AuthState(token_required=bool(token), authenticated=request_authenticated(request.scope, token))


@router.post("/api/login", response_model=AuthState, responses={401: {"description": "missing or invalid token"}})
def login(request: Request, response: Response) -> AuthState:
    """Exchange the bearer token for a session cookie (``HttpOnly; SameSite=Strict``)."""
    token = request.app.state.settings.api_token
    if token:  # the middleware let this POST through only with the right bearer token
        response.headers.append("set-cookie", token_cookie(token, secure=request.url.scheme == "https"))
    return AuthState(token_required=bool(token), authenticated=True)


@router.post("/api/logout", response_model=AuthState)
def logout(request: Request, response: Response) -> AuthState:
    """Forget the session cookie (open)."""
    response.delete_cookie(TOKEN_COOKIE, path="/", httponly=True, samesite="strict")
    token = request.app.state.settings.api_token
    return AuthState(token_required=bool(token), authenticated=not token)
