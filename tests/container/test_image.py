"""The Docker image, built and run for real with podman (see ../shared/container-testing.md).

Builds ``Dockerfile`` on ``python:3.11-slim`` (a local stand-in made by
``../shared/scripts/container-base-image.sh`` when no registry is reachable), runs
it as users would (token in the environment, a data volume), and checks from outside
the container: ``/api/status``, the dashboard page, ``/viser/``, the token rules, a
recording landing in the volume, the health check, the non-root user, and the refusal
to start on 0.0.0.0 without a token.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

pytestmark = [pytest.mark.container, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
BASE_SCRIPT = REPO.parent / "shared" / "scripts" / "container-base-image.sh"
BASE_IMAGE = "python:3.11-slim"
IMAGE = "fringescope"
PODMAN = ["podman", "--storage-driver=vfs"]
RUN = [*PODMAN, "run", "--runtime", "runc", "--network", "host",
       "--ulimit", "nofile=1024:1024", "--ulimit", "nproc=1024:1024"]
TOKEN = "container-test-token-7f3a"


def podman(
    *args: str, timeout: float = 300, check: bool = True
) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run([*PODMAN, *args], capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(
            f"podman {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}"
        )
    return proc


def image_id(name: str) -> str | None:
    proc = podman("image", "inspect", "--format", "{{.Id}}", name, check=False)
    return proc.stdout.strip() or None if proc.returncode == 0 else None


def ensure_base_image() -> None:
    if shutil.which("podman") is None:
        pytest.skip(
            "podman is not installed (make test installs it: scripts/install-system-deps.sh)"
        )
    if podman("image", "exists", BASE_IMAGE, check=False).returncode != 0:
        if not BASE_SCRIPT.is_file():
            pytest.skip(f"no {BASE_IMAGE} image and no {BASE_SCRIPT} to make a local stand-in")
        proc = subprocess.run(
            ["bash", str(BASE_SCRIPT)], capture_output=True, text=True, timeout=1200
        )
        assert proc.returncode == 0, f"{BASE_SCRIPT} failed:\n{proc.stderr[-3000:]}"
    # The stand-in is imported from a mktemp -d folder, so its "/" may be mode 0700, which
    # no non-root user can traverse (the official image has 0755). Re-import it with 0755.
    probe = podman(
        "run",
        "--rm",
        "--runtime",
        "runc",
        "--network",
        "host",
        "--ulimit",
        "nofile=1024:1024",
        "--ulimit",
        "nproc=1024:1024",
        "--user",
        "root",
        BASE_IMAGE,
        "stat",
        "-c",
        "%a",
        "/",
        check=False,
    )
    if probe.stdout.strip() == "700":
        with tempfile.TemporaryDirectory(prefix="fs-base-") as root:
            Path(root).chmod(0o755)
            name = f"fs-basefix-{int(time.time())}"
            podman("create", "--name", name, BASE_IMAGE, "/bin/true")
            try:
                export = subprocess.Popen([*PODMAN, "export", name], stdout=subprocess.PIPE)
                subprocess.run(
                    ["tar", "-C", root, "-x"], stdin=export.stdout, check=True, timeout=600
                )
                assert export.wait(60) == 0
            finally:
                podman("rm", "-f", name, check=False)
            tar = subprocess.Popen(["tar", "-C", root, "-c", "."], stdout=subprocess.PIPE)
            subprocess.run([*PODMAN, "import", "-", f"localhost/{BASE_IMAGE}"], stdin=tar.stdout,
                           check=True, capture_output=True, timeout=600)
            assert tar.wait(60) == 0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def http(method: str, url: str, *, token: str | None = None, body: dict[str, object] | None = None,
         timeout: float = 10) -> tuple[int, dict[str, str], bytes]:
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method)
    if data is not None:
        req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


@pytest.fixture(scope="module")
def built_image() -> Iterator[str]:
    ensure_base_image()
    old = image_id(IMAGE)
    t0 = time.monotonic()
    # --layers=false: one working container, one commit (each layer is a full copy on vfs)
    podman("build", "--pull=never", "--isolation=chroot", "--format", "docker", "--layers=false",
           "-t", IMAGE, str(REPO), timeout=1800)
    build_s = time.monotonic() - t0
    print(f"\nimage build: {build_s:.0f} s")
    new = image_id(IMAGE)
    if old and new != old:
        podman("rmi", old, check=False)  # each stale image is a full gigabyte copy on vfs
    yield IMAGE


def test_image_refuses_to_listen_without_token(built_image: str) -> None:
    proc = subprocess.run([*RUN, "--rm", "-e", f"FRINGESCOPE_PORT={free_port()}", built_image],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert "refusing to listen on 0.0.0.0 without FRINGESCOPE_API_TOKEN" in proc.stderr


def test_image_serves_dashboard_viewer_and_api(built_image: str, tmp_path: Path) -> None:
    port = free_port()
    name = f"fringescope-test-{port}"
    data = tmp_path / "data"
    data.mkdir()
    data.chmod(0o777)  # the container's user (uid 10001) writes here
    base = f"http://127.0.0.1:{port}"
    podman("run", "--runtime", "runc", "--network", "host", "--ulimit", "nofile=1024:1024",
           "--ulimit", "nproc=1024:1024", "-d", "--name", name, "-v", f"{data}:/data",
           "-e", f"FRINGESCOPE_PORT={port}", "-e", f"FRINGESCOPE_API_TOKEN={TOKEN}",
           "-e", "FRINGESCOPE_SIM_SEED=3", built_image)
    try:
        deadline = time.monotonic() + 300
        status: dict[str, object] = {}
        while time.monotonic() < deadline:
            try:
                code, _, body = http("GET", f"{base}/api/status", token=TOKEN, timeout=5)
                if code == 200:
                    status = json.loads(body)
                    break
            except OSError:
                pass
            running = podman("inspect", "--format", "{{.State.Running}}", name, check=False)
            assert running.stdout.strip() == "true", podman("logs", name, check=False).stderr[
                -3000:
            ]
            time.sleep(2)
        assert status, (
            f"no /api/status within 300 s:\n{podman('logs', name, check=False).stderr[-3000:]}"
        )
        assert status["state"] in ("starting", "calibrating", "running", "stalled", "fault")
        assert any(d["kind"] == "camera" and d["name"].startswith("sim") for d in status["devices"])  # type: ignore[attr-defined]

        # off loopback the data routes need the token; /healthz stays open
        assert http("GET", f"{base}/api/status")[0] == 401
        assert http("GET", f"{base}/healthz")[0] == 200
        code, headers, body = http("GET", f"{base}/")
        assert code == 200 and headers["content-type"].startswith("text/html")
        assert b"<html" in body.lower() and b"fringescope" in body.lower()

        # the viewer relay needs the token; ?token= lets a browser in (and sets the cookie)
        assert http("GET", f"{base}/viser/")[0] == 401
        code, headers, body = http("GET", f"{base}/viser/?token={TOKEN}")
        assert code == 200 and b"<html" in body.lower()
        assert "fringescope_token=" in headers.get("set-cookie", headers.get("Set-Cookie", ""))

        # state changes need the bearer token
        code, _, body = http("PUT", f"{base}/api/exposure", body={"exposure_ms": 12})
        assert code == 401 and json.loads(body)["detail"]
        assert http("PUT", f"{base}/api/exposure", token=TOKEN, body={"exposure_ms": 12})[0] == 200

        # a recording lands in the volume, owned by the container's non-root user
        code, _, body = http(
            "POST", f"{base}/api/recording/start", token=TOKEN, body={"name": "vol"}
        )
        assert code == 200, body
        session = data / "recordings" / "vol" / "session.json"
        assert session.is_file()
        time.sleep(3)
        code, _, body = http("POST", f"{base}/api/recording/stop", token=TOKEN)
        assert code == 200 and json.loads(body)["stopped"]["name"] == "vol"
        assert json.loads(session.read_text())["stopped"] is not None
        assert session.stat().st_uid == 10001

        uid = podman("exec", name, "id", "-u").stdout.strip()
        assert uid == "10001"
        health = podman("healthcheck", "run", name, check=False, timeout=60)
        assert health.returncode == 0, health.stderr
    finally:
        podman("stop", "-t", "20", name, check=False, timeout=120)
        logs = podman("logs", name, check=False).stderr
        podman("rm", "-f", name, check=False, timeout=120)
    assert "Traceback" not in logs, logs[-3000:]
