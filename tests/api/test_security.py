"""Security middleware on a real FastAPI app: token, startup refusal, CORS, Origin, uploads."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi import FastAPI, HTTPException, Request, UploadFile, WebSocket
from fastapi.testclient import TestClient
from pydantic import BaseModel
from starlette.websockets import WebSocketDisconnect

from app.api.security import (
    MIN_TOKEN_CHARS,
    TOKEN_COOKIE,
    check_startup_security,
    checked_name,
    install_security,
    is_loopback,
)
from app.config import Settings

TOKEN = "s3cret-token_0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class Exposure(BaseModel):
    exposure_ms: float


def make_app(**settings: object) -> FastAPI:
    app = FastAPI()

    @app.get("/api/status")
    def status() -> dict[str, str]:
        return {"state": "running"}

    @app.put("/api/exposure")
    def exposure(body: Exposure) -> dict[str, float]:
        return {"exposure_ms": body.exposure_ms}

    @app.delete("/api/recordings/{name}")
    def delete(name: str) -> dict[str, str]:
        return {"deleted": checked_name(name, "recording name")}

    @app.post("/api/raw")
    async def raw(request: Request) -> dict[str, int]:
        return {"bytes": len(await request.body())}

    @app.post("/api/file")
    async def file(upload: UploadFile) -> dict[str, int]:
        return {"bytes": len(await upload.read())}

    @app.get("/viser/")
    def viewer_page() -> dict[str, str]:
        return {"page": "viser"}

    @app.websocket("/viser/ws")
    async def viewer_ws(ws: WebSocket) -> None:
        await ws.accept()
        await ws.send_text("hello")
        await ws.close()

    @app.websocket("/api/stream")
    async def stream(ws: WebSocket) -> None:
        await ws.accept()
        await ws.send_text("frame")
        await ws.close()

    install_security(app, Settings(**settings))  # type: ignore[arg-type]
    return app


def test_startup_refuses_exposed_without_token() -> None:
    with pytest.raises(ValueError) as err:
        check_startup_security(Settings(host="0.0.0.0"))
    assert str(err.value) == (
        "refusing to listen on 0.0.0.0 without FRINGESCOPE_API_TOKEN (use --insecure to override)"
    )
    with pytest.raises(ValueError, match="refusing to listen on 192.168.1.7"):
        make_app(host="192.168.1.7")
    check_startup_security(Settings(host="0.0.0.0", insecure=True))
    check_startup_security(Settings(host="0.0.0.0", api_token=TOKEN))
    for host in ("127.0.0.1", "127.0.0.2", "localhost", "::1", "[::1]"):
        assert is_loopback(host)
        check_startup_security(Settings(host=host))
    for host in ("0.0.0.0", "::", "10.0.0.1", "example.org", ""):
        assert not is_loopback(host)
    for bad in ("", "has space", "semi;colon", 'quo"te'):
        with pytest.raises(ValueError, match="api_token"):
            check_startup_security(Settings(api_token=bad))
    for short in ("x", "a" * (MIN_TOKEN_CHARS - 1)):
        with pytest.raises(ValueError) as err:
            check_startup_security(Settings(api_token=short))
        assert str(err.value) == (f"api_token: FRINGESCOPE_API_TOKEN must have at least "
                                  f"{MIN_TOKEN_CHARS} characters, got {len(short)}")
    check_startup_security(Settings(api_token="a" * MIN_TOKEN_CHARS))
    with pytest.raises(ValueError, match="trusted_proxies: 'proxy.example' is not an IP"):
        check_startup_security(Settings(trusted_proxies=["proxy.example"]))


def test_no_token_on_loopback_leaves_routes_open() -> None:
    client = TestClient(make_app())
    assert client.put("/api/exposure", json={"exposure_ms": 20}).json() == {"exposure_ms": 20.0}
    assert client.get("/viser/").status_code == 200
    with client.websocket_connect("/viser/ws") as ws:
        assert ws.receive_text() == "hello"


def test_token_guards_state_changing_routes() -> None:
    client = TestClient(make_app(api_token=TOKEN))
    # reads need the token too (the open health check is /healthz, see test_access.py)
    assert client.get("/api/status").status_code == 401
    assert client.get("/api/status", headers=AUTH).status_code == 200
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"},
                    {"Authorization": f"Bearer {TOKEN}x"}):
        r = client.put("/api/exposure", json={"exposure_ms": 20}, headers=headers)
        assert r.status_code == 401, headers
        assert "token" in r.json()["detail"] and r.headers["www-authenticate"] == "Bearer"
    assert client.put("/api/exposure", json={"exposure_ms": 20}, headers=AUTH).status_code == 200
    assert client.delete("/api/recordings/abc").status_code == 401
    assert client.delete("/api/recordings/abc", headers=AUTH).json() == {"deleted": "abc"}
    # cookie and query never authorise a state change (cross-site request forgery)
    client.cookies.set(TOKEN_COOKIE, TOKEN)
    assert client.put(f"/api/exposure?token={TOKEN}", json={"exposure_ms": 20}).status_code == 401


def test_viewer_relay_needs_token_by_header_cookie_or_query() -> None:
    client = TestClient(make_app(api_token=TOKEN))
    assert client.get("/viser/").status_code == 401
    assert client.get("/viser/", headers=AUTH).status_code == 200
    with pytest.raises(WebSocketDisconnect) as err, client.websocket_connect("/viser/ws"):
        pass
    assert err.value.code == 1008
    with client.websocket_connect(f"/viser/ws?token={TOKEN}") as ws:
        assert ws.receive_text() == "hello"
    # a valid query token sets the cookie the page's assets and WebSocket then use: a session
    # id, never the token
    r = client.get(f"/viser/?token={TOKEN}")
    assert r.status_code == 200
    assert r.headers["set-cookie"].startswith(f"{TOKEN_COOKIE}=")
    assert TOKEN not in r.headers["set-cookie"] and len(client.cookies[TOKEN_COOKIE]) >= 40
    assert "HttpOnly" in r.headers["set-cookie"] and "SameSite=Strict" in r.headers["set-cookie"]
    assert client.get("/viser/").status_code == 200  # the cookie now travels
    with client.websocket_connect("/viser/ws") as ws:
        assert ws.receive_text() == "hello"
    # read-only streams need the token as well (header, cookie or query)
    fresh = TestClient(make_app(api_token=TOKEN))
    with pytest.raises(WebSocketDisconnect) as err, fresh.websocket_connect("/api/stream"):
        pass
    assert err.value.code == 1008
    with fresh.websocket_connect("/api/stream", headers=AUTH) as ws:
        assert ws.receive_text() == "frame"


def test_websocket_origin_checked() -> None:
    client = TestClient(make_app(api_token=TOKEN, cors_origins=["https://ok.example"]))
    for origin in ("https://evil.example", "http://testserver.evil.example", "null"):
        for path in ("/api/stream", f"/viser/ws?token={TOKEN}"):
            with pytest.raises(WebSocketDisconnect) as err, \
                    client.websocket_connect(path, headers={"origin": origin}):
                pass
            assert err.value.code == 1008
    for origin in ("http://testserver", "https://ok.example"):
        with client.websocket_connect(
            f"/api/stream?token={TOKEN}", headers={"origin": origin}
        ) as ws:
            assert ws.receive_text() == "frame"


def test_cors_closed_by_default_open_when_listed() -> None:
    preflight = {"Origin": "https://ok.example", "Access-Control-Request-Method": "PUT",
                 "Access-Control-Request-Headers": "authorization,content-type"}
    closed = TestClient(make_app(api_token=TOKEN))
    r = closed.options("/api/exposure", headers=preflight)
    assert "access-control-allow-origin" not in r.headers
    r = closed.get("/api/status", headers={"Origin": "https://ok.example"})
    assert "access-control-allow-origin" not in r.headers

    opened = TestClient(make_app(api_token=TOKEN, cors_origins=["https://ok.example"]))
    r = opened.options("/api/exposure", headers=preflight)
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://ok.example"
    r = opened.put("/api/exposure", json={"exposure_ms": 1}, headers={"Origin": "https://ok.example"})
    assert r.status_code == 401 and r.headers["access-control-allow-origin"] == "https://ok.example"
    r = opened.options("/api/exposure", headers={**preflight, "Origin": "https://evil.example"})
    assert "access-control-allow-origin" not in r.headers


def chunks(n_bytes: int, size: int = 256) -> Iterator[bytes]:
    for start in range(0, n_bytes, size):
        yield b"x" * min(size, n_bytes - start)


def test_upload_limit_announced_and_streamed() -> None:
    client = TestClient(make_app(max_upload_mb=0.001))  # 1000 bytes
    assert client.post("/api/raw", content=b"x" * 1000).json() == {"bytes": 1000}
    r = client.post("/api/raw", content=b"x" * 1001)
    assert r.status_code == 413 and "exceeds the limit" in r.json()["detail"]
    # no Content-Length (chunked): counted as it streams in
    r = client.post("/api/raw", content=chunks(5000))
    assert "content-length" not in r.request.headers
    assert r.status_code == 413 and "FRINGESCOPE_MAX_UPLOAD_MB" in r.json()["detail"]
    assert client.post("/api/raw", content=chunks(900)).json() == {"bytes": 900}
    r = client.post("/api/file", files={"upload": ("a.bin", b"y" * 4000)})
    assert r.status_code == 413 and "too large" in r.json()["detail"]
    r = client.put(
        "/api/exposure", content=chunks(3000), headers={"content-type": "application/json"}
    )
    assert r.status_code == 413
    r = client.post("/api/raw", content=b"abc", headers={"content-length": "x"})
    assert r.status_code == 400


def test_checked_name_and_openapi() -> None:
    client = TestClient(make_app(api_token=TOKEN))
    r = client.delete("/api/recordings/..%2F..%2Fetc", headers=AUTH)
    assert r.status_code in (400, 404)
    r = client.delete("/api/recordings/.hidden", headers=AUTH)
    assert r.status_code == 400 and "recording name" in r.json()["detail"]
    with pytest.raises(HTTPException) as err:
        checked_name("a/b")
    assert err.value.status_code == 400
    spec = client.get("/openapi.json").json()
    assert spec["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    assert spec["paths"]["/api/exposure"]["put"]["security"] == [{"bearer": []}]
    assert spec["paths"]["/api/status"]["get"]["security"] == [{"bearer": []}]
