"""``fringescope serve`` as a real process on loopback, fed hostile bodies over TCP.

The figures of issue 25: a PNG decompression bomb (a ~1 MB zip of 16 all-zero 8000 × 8000
PNGs) answered 4xx within 1 s while the server's resident memory grows by at most 100 MB;
a 10 MB JSON body refused within 100 ms while another client's ``/api/status`` is answered;
the same body streamed without ``Content-Length`` refused once the route's limit is passed;
multipart file names of 300 characters answered 4xx. The server's memory is read from
``/proc/PID/status`` (its peak reset through ``/proc/PID/clear_refs`` before each upload).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.helpers.hostile import capture_json, png_bomb_zip, zero_png
from tests.helpers.served import ServedApp, free_port

pytestmark = [pytest.mark.slow, pytest.mark.serial]

MB = 1024 * 1024


def _memory_kb(pid: int) -> dict[str, int]:
    out = {}
    with open(f"/proc/{pid}/status", encoding="ascii") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0])
    return out


def _reset_peak(pid: int) -> None:
    with open(f"/proc/{pid}/clear_refs", "w", encoding="ascii") as fh:
        fh.write("5")  # resets VmHWM to the current RSS


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path
) -> Iterator[tuple[str, int]]:
    """(base URL, pid) of a served app with the simulator's calibration, acquisition stopped."""
    tmp = tmp_path_factory.mktemp("hostile-server")
    port = free_port()
    config = tmp / "fringescope.toml"
    config.write_text("[fringescope]\nautostart = false\nviewer = false\n", encoding="utf-8")
    env = dict(
        os.environ,
        FRINGESCOPE_CALIBRATION_FILE=str(sim_calibration_file),
        NUMBA_THREADING_LAYER="workqueue",
    )
    server = ServedApp(
        ["--port", str(port), "--config", str(config), "--data-dir", str(tmp / "data")],
        env,
        tmp / "server.log",
    )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and server.running():
            try:
                if httpx.get(f"{base}/api/status", timeout=2).json()["calibration"]:
                    break
            except (httpx.HTTPError, KeyError, ValueError):
                pass
            time.sleep(0.3)
        assert server.running(), server.log()
        yield base, server.pid
    finally:
        server.stop()


@pytest.mark.parametrize("route", ["/api/reconstruct", "/api/phase"])
def test_png_bomb_is_refused_from_its_headers(server: tuple[str, int], route: str) -> None:
    base, pid = server
    bomb = png_bomb_zip()
    assert len(bomb) < 1.1 * MB  # ~1 MB that would decode to 16 × 64 MB
    before = _memory_kb(pid)["VmRSS"]
    _reset_peak(pid)
    t0 = time.perf_counter()
    r = httpx.post(
        base + route, content=bomb, headers={"content-type": "application/zip"}, timeout=60
    )
    elapsed_s = time.perf_counter() - t0
    growth_mb = (_memory_kb(pid)["VmHWM"] - before) / 1024
    print(
        f"\n{route}: PNG bomb ({len(bomb) / MB:.2f} MB zip) -> {r.status_code} "
        f"in {elapsed_s * 1000:.0f} ms, "
        f"server peak RSS growth {growth_mb:.1f} MB: {r.json()['detail']}"
    )
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail.startswith("frame_00.png: ") and "8000x8000" in detail, detail
    if route == "/api/reconstruct":
        assert "calibration's 1384x1032" in detail, detail
    assert elapsed_s <= 1.0
    assert growth_mb <= 100


def test_ten_megabyte_json_is_refused_at_once_and_others_are_served(
    server: tuple[str, int],
) -> None:
    base, _ = server
    item = b'{"kind": "length", "points": [[1.5, 2.5], [3.5, 4.5]]}, '
    body = (
        b'{"measurements": ['
        + item * (10 * MB // len(item))
        + b'{"kind": "length", "points": []}]}'
    )
    assert len(body) >= 10 * MB
    status_ms: list[float] = []
    stop = threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=base, timeout=10) as c:
            while not stop.is_set():
                t = time.perf_counter()
                assert c.get("/api/status").status_code == 200
                status_ms.append((time.perf_counter() - t) * 1000)

    poller = threading.Thread(target=poll)
    poller.start()
    try:
        time.sleep(0.3)
        with httpx.Client(base_url=base, timeout=30) as c:
            t0 = time.perf_counter()
            r = c.put(
                "/api/measure/tool", content=body, headers={"content-type": "application/json"}
            )
            elapsed_ms = (time.perf_counter() - t0) * 1000
        time.sleep(0.3)
    finally:
        stop.set()
        poller.join()
    print(
        f"\n10 MB JSON to PUT /api/measure/tool -> {r.status_code} in {elapsed_ms:.0f} ms; "
        "concurrent "
        f"/api/status: {len(status_ms)} answers, max {max(status_ms):.0f} ms"
    )
    assert r.status_code == 413 and "1048576-byte limit" in r.json()["detail"], r.text
    assert elapsed_ms <= 100
    assert len(status_ms) >= 3 and max(status_ms) < 1000


def test_a_streamed_body_is_refused_once_past_the_limit(server: tuple[str, int]) -> None:
    base, _ = server
    sent = 0

    def chunks() -> Iterator[bytes]:  # no Content-Length: chunked transfer
        nonlocal sent
        yield b'{"exposure_ms": 1' + b"0" * 1000
        sent += 1000
        while sent < 10 * MB:
            yield b"0" * 16384
            sent += 16384

    t0 = time.perf_counter()
    try:
        r = httpx.put(
            base + "/api/exposure",
            content=chunks(),
            timeout=30,
            headers={"content-type": "application/json"},
        )
        code, detail = r.status_code, r.json()["detail"]
    except httpx.HTTPError as exc:  # the server may close the connection while we still send
        code, detail = 413, str(exc)
    elapsed_ms = (time.perf_counter() - t0) * 1000
    print(
        f"\nchunked 10 MB to PUT /api/exposure -> {code} after {sent} bytes sent, "
        f"{elapsed_ms:.0f} ms"
    )
    assert code == 413, detail
    assert sent < 10 * MB  # refused before the whole body was sent
    assert httpx.get(base + "/api/status", timeout=10).json()["exposure_ms"] != 1


def test_multipart_file_names_of_300_characters_are_4xx(server: tuple[str, int]) -> None:
    base, _ = server
    long = "f" * 300 + ".png"
    files = [("files", ("capture.json", capture_json(), "application/json"))]
    files += [
        ("files", (long if i == 3 else f"frame_{i:02d}.png", zero_png(8, 8), "image/png"))
        for i in range(16)
    ]
    r = httpx.post(base + "/api/phase", files=files, timeout=30)
    assert r.status_code == 422 and "304 characters long" in r.json()["detail"], r.text
    r = httpx.post(
        base + "/api/phase",
        files=[("files", ("x" * 300 + ".zip", b"PK", "application/zip"))],
        timeout=30,
    )
    assert 400 <= r.status_code < 500 and "\n" not in r.json()["detail"], r.text
