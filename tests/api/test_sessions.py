"""Session cookies that are not the token, the failed-token throttle, the security headers.

The app is the real one (``create_app``, not started: the middleware and the auth routes
answer without the instrument); the trusted-proxy case also runs through a real uvicorn
server on loopback, and the start-up refusal through the real ``fringescope serve``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.api.security import DASHBOARD_CSP, MIN_TOKEN_CHARS, TOKEN_COOKIE
from app.api.sessions import FIRST_HOLD_OFF_S, FREE_FAILURES, FailureThrottle, SessionStore
from app.cli.serve import proxy_options
from app.config import Settings
from app.main import create_app
from tests.helpers.outputs import serve
from tests.helpers.served import free_port

TOKEN = "session-token_0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
PROXY = "10.0.0.9"


def make_app(tmp_path: Path, **overrides: object) -> FastAPI:
    values: dict[str, object] = {"host": "0.0.0.0", "api_token": TOKEN, "data_dir": tmp_path,
                                 "viewer": False}
    values.update(overrides)
    return create_app(Settings(**values))  # type: ignore[arg-type]


def login(client: TestClient) -> tuple[str, str]:
    """(session id, the whole Set-Cookie header) of a fresh login."""
    r = client.post("/api/login", headers=AUTH)
    assert r.status_code == 200, r.text
    header = r.headers["set-cookie"]
    name, _, value = header.split(";")[0].partition("=")
    assert name == TOKEN_COOKIE
    return value, header


def cookie(sid: str) -> dict[str, str]:
    return {"cookie": f"{TOKEN_COOKIE}={sid}"}


def test_the_cookie_is_a_random_session_revoked_at_logout(tmp_path: Path) -> None:
    app = make_app(tmp_path)
    client = TestClient(app)
    sid, header = login(client)
    other, _ = login(TestClient(app))
    assert TOKEN not in header and sid != other and len(sid) >= 40
    assert "HttpOnly" in header and "SameSite=Strict" in header and "Secure" not in header
    assert TestClient(app).get("/api/recordings", headers=cookie(sid)).status_code == 200
    assert TestClient(app).get("/api/recordings", headers=cookie(TOKEN)).status_code == 401
    assert TestClient(app).get("/api/auth", headers=cookie(sid)).json()["authenticated"] is True
    # logout ends the session on the server: the old cookie, sent again, opens nothing
    r = client.post("/api/logout")
    assert r.status_code == 200 and r.json()["authenticated"] is False
    assert TestClient(app).get("/api/recordings", headers=cookie(sid)).status_code == 401
    assert TestClient(app).get("/api/recordings", headers=cookie(other)).status_code == 200


def test_sessions_expire_and_die_when_the_token_changes(tmp_path: Path) -> None:
    app = make_app(tmp_path, session_ttl_s=0.5)
    sid, _ = login(TestClient(app))
    assert TestClient(app).get("/api/recordings", headers=cookie(sid)).status_code == 200
    time.sleep(0.6)
    assert TestClient(app).get("/api/recordings", headers=cookie(sid)).status_code == 401

    app = make_app(tmp_path)
    sid, _ = login(TestClient(app))
    app.state.settings.api_token = "another-token_4567"  # the operator changes the token
    assert TestClient(app).get("/api/recordings", headers=cookie(sid)).status_code == 401
    assert TestClient(app).get("/api/recordings", headers=AUTH).status_code == 401
    r = TestClient(app).get(
        "/api/recordings", headers={"Authorization": "Bearer another-token_4567"}
    )
    assert r.status_code == 200
    # and a restarted server knows no session of the previous one
    fresh = make_app(tmp_path)
    assert TestClient(fresh).get("/api/recordings", headers=cookie(sid)).status_code == 401


def test_session_store_and_throttle_by_the_clock() -> None:
    now = [100.0]
    store = SessionStore(ttl_s=10.0, clock=lambda: now[0])
    sid = store.open(TOKEN)
    assert (
        store.valid(sid, TOKEN)
        and not store.valid(sid, TOKEN + "x")
        and not store.valid("nope", TOKEN)
    )
    now[0] += 9.9
    assert store.valid(sid, TOKEN)
    now[0] += 0.2
    assert not store.valid(sid, TOKEN) and len(store) == 0
    with pytest.raises(ValueError, match="ttl_s"):
        SessionStore(ttl_s=0)

    throttle = FailureThrottle(clock=lambda: now[0])
    for _ in range(FREE_FAILURES):
        throttle.failed("a")
    assert throttle.held_off_s("a") == 0.0
    holds = []
    for _ in range(8):
        throttle.failed("a")
        holds.append(throttle.held_off_s("a"))
    # doubling, capped
    assert holds == pytest.approx([FIRST_HOLD_OFF_S * 2**i for i in range(6)] + [60.0, 60.0])
    assert throttle.held_off_s("b") == 0.0
    throttle.succeeded("a")
    assert throttle.held_off_s("a") == 0.0


def test_wrong_tokens_hold_the_client_off(tmp_path: Path) -> None:
    app = make_app(tmp_path)
    guesser = TestClient(app, client=("192.0.2.7", 5000))
    bystander = TestClient(app, client=("192.0.2.8", 5000))
    for i in range(FREE_FAILURES + 1):
        r = guesser.get("/api/status", headers={"Authorization": f"Bearer guess-{i:012d}"})
        assert r.status_code == 401, (i, r.text)
    t0 = time.monotonic()
    r = guesser.get("/api/status", headers={"Authorization": "Bearer guess-next-000"})
    assert r.status_code == 429 and r.headers["retry-after"] == "1"
    assert r.json()["detail"] == "too many wrong tokens from this client: retry in 1 s"
    # while held off not even the right token is compared (it would confirm a guess)
    assert guesser.get("/api/recordings", headers=AUTH).status_code == 429
    assert guesser.get("/api/auth", headers=AUTH).json()["authenticated"] is False
    with pytest.raises(WebSocketDisconnect) as err, \
            guesser.websocket_connect(f"/api/stream/depth?token={TOKEN}"):
        pass
    assert err.value.code == 1008 and "too many wrong tokens" in err.value.reason
    # other clients are not held off, and no token at all is no attempt
    assert bystander.get("/api/recordings", headers=AUTH).status_code == 200
    assert guesser.get("/api/recordings").status_code == 401
    time.sleep(max(0.0, FIRST_HOLD_OFF_S + 0.05 - (time.monotonic() - t0)))
    assert guesser.get("/api/recordings", headers=AUTH).status_code == 200  # clears the count
    assert (
        guesser.get("/api/status", headers={"Authorization": "Bearer wrong-again-000"}).status_code
        == 401
    )
    spec = guesser.get("/openapi.json").json()
    assert "429" in spec["paths"]["/api/status"]["get"]["responses"]


def test_secure_cookie_over_https_and_from_a_trusted_proxy(tmp_path: Path) -> None:
    app = make_app(tmp_path, trusted_proxies=[PROXY])
    _, header = login(TestClient(app, base_url="https://testserver"))
    assert "; Secure" in header
    forwarded = {"X-Forwarded-Proto": "https", "X-Forwarded-For": "198.51.100.4"}
    r = TestClient(app, client=(PROXY, 4000)).post("/api/login", headers={**AUTH, **forwarded})
    assert "; Secure" in r.headers["set-cookie"]
    r = TestClient(app, client=("192.0.2.50", 4000)).post(
        "/api/login", headers={**AUTH, **forwarded}
    )
    assert "Secure" not in r.headers["set-cookie"]  # anyone can send the header
    # behind the proxy every client is throttled on its own forwarded address
    for i in range(FREE_FAILURES + 1):
        TestClient(app, client=(PROXY, 4000)).get(
            "/api/status", headers={"Authorization": f"Bearer guess-{i:012d}", **forwarded})
    held = TestClient(app, client=(PROXY, 4000)).get("/api/status", headers={**AUTH, **forwarded})
    assert held.status_code == 429
    other = {**forwarded, "X-Forwarded-For": "198.51.100.5"}
    assert (
        TestClient(app, client=(PROXY, 4000))
        .get("/api/recordings", headers={**AUTH, **other})
        .status_code
        == 200
    )


@pytest.fixture()
def served(tmp_path: Path, sim_calibration_file: Path) -> Iterator[str]:
    """The app behind a real uvicorn on loopback, configured as ``fringescope serve`` does (with
    a calibration: without one the simulator's calibration starts, and shutting down waits
    for it)."""
    settings = Settings(
        api_token=TOKEN, data_dir=tmp_path, viewer=False, trusted_proxies=["127.0.0.1"],
        calibration_file=sim_calibration_file,
    )
    with serve(create_app(settings), **proxy_options(settings.trusted_proxies)) as host:
        yield f"http://{host}"


def test_real_server_behind_a_tls_proxy_sets_secure(served: str) -> None:
    r = httpx.post(
        f"{served}/api/login", headers={**AUTH, "X-Forwarded-Proto": "https"}, timeout=30
    )
    assert r.status_code == 200 and "; Secure" in r.headers["set-cookie"]
    r = httpx.post(f"{served}/api/login", headers=AUTH, timeout=30)
    assert r.status_code == 200 and "Secure" not in r.headers["set-cookie"]
    page = httpx.get(f"{served}/", timeout=30)
    assert page.status_code == 200 and page.headers["content-security-policy"] == DASHBOARD_CSP


def test_security_headers_on_the_dashboard(tmp_path: Path) -> None:
    client = TestClient(make_app(tmp_path))
    for path in ("/", "/index.html", "/auth.js", "/js/main.js", "/style.css"):
        r = client.get(path)
        assert r.status_code == 200, path
        assert r.headers["content-security-policy"] == DASHBOARD_CSP, path
        assert "frame-ancestors 'self'" in DASHBOARD_CSP and "script-src 'self'" in DASHBOARD_CSP
        assert r.headers["x-frame-options"] == "SAMEORIGIN"
        assert r.headers["x-content-type-options"] == "nosniff"
        assert r.headers["referrer-policy"] == "no-referrer"
    for path in ("/api/status", "/healthz", "/docs"):  # not the dashboard: no page policy
        r = client.get(path)
        assert r.headers["x-content-type-options"] == "nosniff", path
        assert "content-security-policy" not in r.headers, path


def test_serve_refuses_a_short_token_in_one_line(tmp_path: Path) -> None:
    env = dict(
        os.environ,
        FRINGESCOPE_API_TOKEN="x" * (MIN_TOKEN_CHARS - 1),
        FRINGESCOPE_VIEWER="false",
        NUMBA_THREADING_LAYER="workqueue",
    )
    r = subprocess.run([sys.executable, "-m", "app", "serve", "--port", str(free_port()),
                        "--data-dir", str(tmp_path / "data")],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert f"at least {MIN_TOKEN_CHARS} characters" in lines[0]
