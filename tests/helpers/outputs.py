"""Test helpers for the viewer: an analytic surface source and a real uvicorn server.

``SurfaceSource`` publishes real :class:`LiveResult` objects into a real
:class:`LatestSlot`, with the control methods the viewer calls; it stands in for the
Instrument only in the viewer's unit tests (the browser tests use the real one).
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import uvicorn
from fastapi import FastAPI

from app.service.reconstruction import LiveResult
from app.service.store import LatestSlot
from tests.helpers.served import free_port

FOCAL_PX = 800.0
PLANE_Z_MM = 60.0  # reference plane (height 0) distance from the camera


def surface_result(height: int = 120, width: int = 160, bump_mm: float = 10.0,
                   shift_px: float = 0.0, invalid_border: int = 5) -> LiveResult:
    """A Gaussian bump of ``bump_mm`` on the reference plane, seen by a pinhole camera.

    Height above the plane is ``bump_mm·exp(-r²/(2σ²))`` (σ = width/8 px, centre shifted
    by ``shift_px``); points are the exact back-projection; a border of
    ``invalid_border`` pixels is invalid (NaN).
    """
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    cx, cy = width / 2 + shift_px, height / 2
    sigma = width / 8
    depth = (bump_mm * np.exp(-((u - cx) ** 2 + (v - cy) ** 2) / (2 * sigma**2))).astype(np.float32)
    z = PLANE_Z_MM - depth
    points = np.stack([(u - width / 2) * z / FOCAL_PX, (v - height / 2) * z / FOCAL_PX, z], axis=-1)
    valid = np.zeros((height, width), bool)
    b = invalid_border
    valid[b:height - b, b:width - b] = True
    depth[~valid] = np.nan
    points = points.astype(np.float32)
    points[~valid] = np.nan
    texture = (40.0 + 180.0 * u / width).astype(np.float32)
    now = time.monotonic()
    return LiveResult(
        depth=depth, points=points, valid=valid, reason=np.where(valid, 0, 1).astype(np.uint8),
        texture=texture, modulation=np.full_like(texture, 50.0), motion=None, mode="set",
        frame_indices=list(range(16)), timestamps=[now] * 16, exposure_ms=30.0, led="green",
        full_scale=255.0, received_s=now, published_s=now, recon_ms=1.0,
    )


class SurfaceSource:
    """Latest-result slot plus the control surface the viewer uses (validating like the
    Instrument)."""

    def __init__(self) -> None:
        self.store: LatestSlot[LiveResult] = LatestSlot()
        self.exposure_ms = 30.0
        self.led = "green"
        self.calls: list[tuple[str, Any]] = []

    def publish(self, result: LiveResult) -> int:
        result.seq = self.store.seq + 1
        return self.store.publish(result)

    def set_exposure(self, exposure_ms: float) -> float:
        if not 1.0 <= exposure_ms <= 100.0:
            raise ValueError(f"exposure_ms: must be within 1–100 ms, got {exposure_ms}")
        self.calls.append(("set_exposure", exposure_ms))
        self.exposure_ms = float(exposure_ms)
        return self.exposure_ms

    def set_led(self, led: str) -> str:
        if led not in ("red", "green", "blue"):
            raise ValueError(f"led: must be red, green or blue, got {led!r}")
        self.calls.append(("set_led", led))
        self.led = led
        return led

    def status(self) -> dict[str, Any]:
        return {"state": "running", "exposure_ms": self.exposure_ms, "led": self.led,
                "depth_fps": 2.0, "camera_fps": 32.0, "latency_ms": 5.0}


def port_is_free(port: int) -> bool:
    """Nothing listens on ``port`` and a new server could bind it.

    SO_REUSEADDR as every server sets it: closed connections may linger in TIME_WAIT.
    """
    with socket.socket() as probe:
        probe.settimeout(1.0)
        if probe.connect_ex(("127.0.0.1", port)) == 0:
            return False
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            s.listen()
        except OSError:
            return False
        return True


def wait_for(predicate: Any, timeout_s: float = 10.0, interval_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    return bool(predicate())


@contextmanager
def serve(app: FastAPI, **options: Any) -> Iterator[str]:
    """Run ``app`` with a real uvicorn on a free loopback port; yields ``host:port``.
    ``options``: more ``uvicorn.Config`` arguments (e.g. the proxy headers)."""
    port = free_port()
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", **options)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="test-uvicorn", daemon=True)
    thread.start()
    try:
        if not wait_for(lambda: server.started or not thread.is_alive(), 60.0):
            raise RuntimeError("uvicorn did not start")
        if not server.started:
            raise RuntimeError("uvicorn exited during startup")
        yield f"127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(30.0)
