"""Helpers for tests against the live app on the simulator: its settings and status polls."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
