"""Off loopback every route that returns or changes data needs the token (issue 16).

The routes are generated, never listed by hand: every operation of the app's OpenAPI
document, plus everything the document leaves out (the viewer relay, WebSockets, the
static dashboard, the docs) found by walking ``app.routes``. A non-loopback bind is
simulated as in ``test_security.py``: ``Settings(host="0.0.0.0", api_token=…)`` — the
middleware decides by the settings, not by the client's address.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.websockets import WebSocketDisconnect

from app.api.security import TOKEN_COOKIE
from app.config import Settings
from app.main import STATIC_DIR, create_app

TOKEN = "access-token_42"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: no data in these (documented in app/api/security.py and the README)
OPEN_OPERATIONS = {("GET", "/healthz"), ("GET", "/api/auth"), ("POST", "/api/logout")}
DOCS = {"/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc"}


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    data = tmp_path_factory.mktemp("access")
    # built, not started: the middleware answers before any route runs
    app = create_app(Settings(host="0.0.0.0", api_token=TOKEN, data_dir=data, viewer=True))
    app.state.instrument.results.close()  # streams end at once instead of waiting for results
    return app


@pytest.fixture()
def client(app: FastAPI) -> Iterator[TestClient]:
    # no ``with``: the lifespan (the instrument) is not started
    yield TestClient(app, raise_server_exceptions=False)


def concrete(path: str) -> str:
    """A path template with sample values: ``{index}`` → 0, ``{name}`` → a valid name."""
    path = re.sub(r"\{index\}", "0", path)
    path = re.sub(r"\{path:path\}", "index.html", path)
    return re.sub(r"\{[^}]+\}", "sample", path)


def session_cookie(client: TestClient) -> str:
    """``name=value`` of a fresh session cookie from ``POST /api/login`` (by another client:
    ``client`` keeps no cookie)."""
    r = TestClient(client.app).post("/api/login", headers=AUTH)
    assert r.status_code == 200, r.text
    return r.headers["set-cookie"].split(";")[0]


def openapi_operations(app: FastAPI) -> list[tuple[str, str]]:
    ops = []
    for path, item in app.openapi()["paths"].items():
        for method in item:
            if method.upper() in {"GET", "PUT", "POST", "DELETE", "PATCH", "HEAD"}:
                ops.append((method.upper(), path))
    return sorted(ops)


def all_routes(app: FastAPI) -> list[Any]:
    """Every leaf route of the app (included routers flattened), with its full path."""
    out: list[Any] = []

    def walk(routes: list[Any], prefix: str) -> None:
        for r in routes:
            inner = getattr(r, "original_router", None)
            if inner is not None:
                walk(inner.routes, prefix + getattr(r.include_context, "prefix", ""))
            elif isinstance(r, (Mount, Route, WebSocketRoute)):
                out.append((prefix + r.path, r))

    walk(app.router.routes, "")
    return out


def test_every_openapi_operation_needs_the_token(app: FastAPI, client: TestClient) -> None:
    ops = openapi_operations(app)
    assert len(ops) >= 30  # the document really was walked
    spec = app.openapi()
    for method, path in ops:
        url = concrete(path)
        if (method, path) in OPEN_OPERATIONS:
            assert client.request(method, url).status_code not in (401, 403), (method, path)
            continue
        r = client.request(method, url)
        assert r.status_code == 401, (method, path, r.status_code)
        assert r.headers["www-authenticate"] == "Bearer" and "token" in r.json()["detail"]
        wrong = client.request(method, url, headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401, (method, path)
        ok = client.request(method, url, headers=AUTH)
        assert ok.status_code not in (401, 403), (method, path, ok.status_code, ok.text[:200])
        assert ok.status_code < 500 or ok.status_code in (503, 507), (
            method,
            path,
            ok.status_code,
            ok.text[:200],
        )
        op = spec["paths"][path][method.lower()]
        assert op.get("security") == [{"bearer": []}] and "401" in op["responses"], (method, path)


def test_routes_outside_openapi_websockets_viewer_static(app: FastAPI, client: TestClient) -> None:
    in_spec = {p for _, p in openapi_operations(app)}
    others = [(p, r) for p, r in all_routes(app) if p not in in_spec]
    kinds = {type(r).__name__ for _, r in others}
    assert any(isinstance(r, WebSocketRoute) for _, r in others) and any(
        isinstance(r, Mount) for _, r in others
    ), kinds
    checked = 0
    for path, route in others:
        if isinstance(route, WebSocketRoute):
            url = concrete(path)
            with pytest.raises(WebSocketDisconnect) as err, client.websocket_connect(url):
                pass
            assert err.value.code == 1008, path
            # with the token (header or session cookie) the handshake passes the middleware;
            # the route itself may then close (instrument not started, viewer not running)
            for kwargs in ({"headers": AUTH}, {"headers": {"cookie": session_cookie(client)}}):
                try:
                    with client.websocket_connect(url, **kwargs):
                        pass
                except WebSocketDisconnect as exc:
                    assert exc.reason != "missing or invalid token", (path, exc.reason)
            checked += 1
        elif isinstance(route, Mount):  # the dashboard: static files, no data in them
            assert route.path in ("", "/")
            files = sorted(p.name for p in Path(STATIC_DIR).iterdir() if p.is_file())
            assert "index.html" in files and "auth.js" in files
            for name in ["", *files]:
                r = client.get("/" + name)
                assert r.status_code == 200, name
            checked += 1
        elif path in DOCS:
            assert client.get(path).status_code == 200, path
            checked += 1
        else:  # e.g. the viewer relay's HTTP routes
            url = concrete(path)
            assert client.get(url, follow_redirects=False).status_code == 401, path
            assert client.get(url, headers=AUTH, follow_redirects=False).status_code not in (
                401,
                403,
            ), path
            cookie = {"cookie": session_cookie(client)}
            assert client.get(url, headers=cookie, follow_redirects=False).status_code not in (
                401,
                403,
            ), path
            # the token itself as the cookie opens nothing: the cookie is a session id
            as_cookie = {"cookie": f"{TOKEN_COOKIE}={TOKEN}"}
            assert client.get(url, headers=as_cookie, follow_redirects=False).status_code == 401, (
                path
            )
            checked += 1
    assert checked == len(others)
    assert any(p.startswith("/viser") for p, _ in others)


def test_login_cookie_opens_reads_and_streams_not_writes(client: TestClient) -> None:
    assert client.get("/api/auth").json() == {"token_required": True, "authenticated": False}
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.post("/api/login").status_code == 401
    r = client.post("/api/login", headers=AUTH)
    assert r.status_code == 200 and r.json()["authenticated"] is True
    cookie = r.headers["set-cookie"]
    assert cookie.startswith(f"{TOKEN_COOKIE}=") and TOKEN not in cookie
    # plain HTTP
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and "Secure" not in cookie
    # a browser-session cookie
    assert "expires" not in cookie.lower() and "max-age" not in cookie.lower()
    assert client.get("/api/auth").json() == {"token_required": True, "authenticated": True}
    assert client.get("/api/status").status_code not in (401, 403)
    assert client.get("/api/recordings").status_code == 200
    assert client.get("/api/stream/depth.mjpeg?frames=1").status_code != 401
    assert client.get("/viser/").status_code != 401
    # the cookie never authorises a state change, nor does a query token
    assert client.put("/api/exposure", json={"exposure_ms": 20}).status_code == 401
    assert client.post(f"/api/recording/start?token={TOKEN}", json={}).status_code == 401
    # a query token opens the viewer and WebSockets only, never the REST reads
    fresh = TestClient(client.app)
    assert fresh.get(f"/api/recordings?token={TOKEN}").status_code == 401
    r = client.post("/api/logout")
    assert r.status_code == 200 and TOKEN_COOKIE in r.headers["set-cookie"]
    assert client.get("/api/recordings").status_code == 401


def test_without_token_on_loopback_everything_stays_open(tmp_path: Path) -> None:
    app = create_app(Settings(data_dir=tmp_path, viewer=False))
    c = TestClient(app)
    assert c.get("/api/auth").json() == {"token_required": False, "authenticated": True}
    assert c.get("/api/recordings").status_code == 200
    assert c.post("/api/login").json()["token_required"] is False
