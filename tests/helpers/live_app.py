"""Helpers for tests against the live app on the simulator: its settings and status polls."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.config import Settings

# the paper's range; the simulator renders each frame well within the period
LIVE_EXPOSURE_MS = 30.0
LIVE_SCENE = "dof_target"  # static: cheap to render, and has a known truth


def live_settings(tmp_path: Path, calibration_file: Path | None, **overrides: Any) -> Settings:
    values: dict[str, Any] = {
        "data_dir": tmp_path / "data", "calibration_file": calibration_file, "viewer": False,
        "sim_seed": 1, "exposure_ms": LIVE_EXPOSURE_MS, "sim_scene": LIVE_SCENE,
    }
    values.update(overrides)
    return Settings(**values)


def wait_for(client: TestClient, predicate: Callable[[dict[str, Any]], bool], timeout_s: float,
             what: str = "condition") -> dict[str, Any]:
    """Poll /api/status until ``predicate(status)`` holds; fail with the last status."""
    deadline = time.monotonic() + timeout_s
    st: dict[str, Any] = {}
    while time.monotonic() < deadline:
        st = client.get("/api/status").json()
        if predicate(st):
            return st
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}; last status: {st}")


def wait_result(client: TestClient, predicate: Callable[[dict[str, Any]], bool], timeout_s: float,
                what: str = "result") -> dict[str, Any]:
    """Poll /api/result/latest until ``predicate(meta)`` holds."""
    deadline = time.monotonic() + timeout_s
    meta: dict[str, Any] = {}
    while time.monotonic() < deadline:
        r = client.get("/api/result/latest")
        if r.status_code == 200:
            meta = r.json()
            if predicate(meta):
                return meta
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}; last result: {meta}")


def capture_after_change(client: TestClient) -> dict[str, Any]:
    """Let two whole sets pass (frames in flight may predate the change), then capture a
    calibration pose through the session API."""
    done = client.get("/api/status").json()["sets_completed"]
    wait_for(client, lambda s: s["sets_completed"] >= done + 2, 60, "two sets after the change")
    r = client.post("/api/calibration/session/poses")
    assert r.status_code == 200, r.text
    result: dict[str, Any] = r.json()
    return result


def app_on_virtual_clock(settings: Settings, scene: str, seed: int = 1) -> FastAPI:
    """The real app whose simulated devices run on a virtual clock (``realtime=False``): a
    scene that renders slower than real time on a loaded machine still gives whole sets,
    where a real-time camera would drop frames until no set is whole."""
    from app.devices.sim.devices import create_sim_devices
    from app.main import create_app
    from app.service.devices import DeviceBundle

    app = create_app(settings)
    sim = create_sim_devices(scene=scene, seed=seed, realtime=False)
    app.state.instrument.pipeline.devices = DeviceBundle(sim.camera, sim.projector,
                                                         sim.controller, sim.world)
    return app
