"""Streams hold no worker thread, and a client holds at most ``max_streams_per_client``.

A real uvicorn server on loopback (the app built on the simulator, acquisition stopped:
the streams wait for depth, which is all the cap needs); real sockets, raw HTTP and WebSocket
handshakes.
"""

from __future__ import annotations

import base64
import json
import secrets
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import FrameType

import httpx
import pytest
from fastapi import FastAPI

from app.config import Settings
from app.main import create_app
from tests.helpers.outputs import serve

pytestmark = pytest.mark.serial  # status answer times compared: alone on the machine

CAP = 3


@pytest.fixture()
def server(tmp_path: Path, sim_calibration_file: Path) -> Iterator[tuple[str, FastAPI]]:
    # with a calibration, nothing calibrates in the background: without one the simulator's
    # calibration starts, and shutting the app down waits for it (uvicorn's thread outlived
    # the fixture's 30 s join, the calibration went on during the next tests)
    app = create_app(Settings(data_dir=tmp_path, viewer=False, autostart=False,
                              calibration_file=sim_calibration_file,
                              max_streams_per_client=CAP))
    with serve(app) as host:
        yield host, app


def _open(host: str, request: str) -> tuple[socket.socket, bytes]:
    """A raw connection sending ``request``; returns it and the answer's head."""
    h, p = host.split(":")
    sock = socket.create_connection((h, int(p)), timeout=10)
    sock.sendall(request.encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk:
            break
        head += chunk
    return sock, head


def _mjpeg(host: str) -> tuple[socket.socket, bytes]:
    return _open(host, f"GET /api/stream/depth.mjpeg HTTP/1.1\r\nHost: {host}\r\n\r\n")


def _ws(host: str) -> tuple[socket.socket, bytes]:
    key = base64.b64encode(secrets.token_bytes(16)).decode()
    return _open(
        host,
        f"GET /api/stream/depth HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\n"
        f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n",
    )


def test_streams_over_the_cap_get_429_and_free_their_slot(server: tuple[str, FastAPI]) -> None:
    host, _ = server
    held = [_mjpeg(host), _ws(host), _mjpeg(host)]
    assert held[0][1].startswith(b"HTTP/1.1 200") and b"multipart/x-mixed-replace" in held[0][1]
    assert held[1][1].startswith(b"HTTP/1.1 101")
    assert held[2][1].startswith(b"HTTP/1.1 200")
    try:
        r = httpx.get(f"http://{host}/api/stream/depth.mjpeg", timeout=10)
        assert r.status_code == 429 and r.headers["retry-after"] == "5"
        assert r.json()["detail"].startswith("too many streams from this client: at most 3 at once")
        sock, head = _ws(host)
        sock.close()
        assert head.startswith(b"HTTP/1.1 429"), head[:200]
        assert b"too many streams" in head or b"429" in head
        # control and status still answer at once while the streams wait for depth
        t0 = time.perf_counter()
        assert httpx.get(f"http://{host}/api/status", timeout=10).status_code == 200
        assert time.perf_counter() - t0 < 1.0
    finally:
        for sock, _ in held[:2]:
            sock.close()
    # the closed streams' slots come back (the server notices the disconnects)
    deadline = time.monotonic() + 10
    while True:
        sock, head = _mjpeg(host)
        sock.close()
        if head.startswith(b"HTTP/1.1 200") or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert head.startswith(b"HTTP/1.1 200"), head[:200]
    held[2][0].close()


def _status_times(host: str, n: int = 21) -> list[float]:
    """Sorted durations (s) of ``n`` GET /api/status, one after another."""
    times = []
    with httpx.Client(timeout=10) as client:
        for _ in range(n):
            t0 = time.perf_counter()
            r = client.get(f"http://{host}/api/status")
            times.append(time.perf_counter() - t0)
            assert r.status_code == 200 and json.loads(r.text)["state"]
    return sorted(times)


def _threads_waiting_on_the_result_slot() -> int:
    """Threads of this process blocked in ``LatestSlot.wait_newer`` (app/service/store.py)."""
    n = 0
    for frame in sys._current_frames().values():
        f: FrameType | None = frame
        while f is not None:
            if f.f_code.co_name == "wait_newer" and f.f_code.co_filename.endswith("store.py"):
                n += 1
                break
            f = f.f_back
    return n


def test_many_streams_hold_no_worker_thread(server: tuple[str, FastAPI]) -> None:
    """More streams than the thread pool has workers (40), from distinct addresses: status
    answers within its usual time, and no stream occupies a worker thread."""
    host, _ = server
    h, p = host.split(":")
    before = _status_times(host)
    socks = []
    try:
        for i in range(45):  # 127.0.0.x: a client each, so the cap does not refuse them
            sock = socket.socket()
            sock.settimeout(10)
            sock.bind((f"127.0.0.{2 + i}", 0))
            sock.connect((h, int(p)))
            sock.sendall(f"GET /api/stream/depth.mjpeg HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
            assert sock.recv(4096).startswith(b"HTTP/1.1 200")
            socks.append(sock)
        time.sleep(1.0)  # every stream is waiting for depth now
        assert _threads_waiting_on_the_result_slot() <= 1  # the one feed thread
        during = _status_times(host)
        # as fast as without streams (a stream holding a worker would queue status behind it)
        assert during[10] < 2 * before[10] + 0.05, (before, during)
        assert during[-1] < 2 * before[-1] + 0.5, (before, during)
    finally:
        for sock in socks:
            sock.close()
