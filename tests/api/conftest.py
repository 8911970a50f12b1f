"""Live-app fixtures: the real app with its lifespan on the simulator.

The calibration is made once per session the way a user would make it (simulated board
poses → ``calibrate_folder``) and handed to every app through ``calibration_file``, so
no app spends its start-up calibrating.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

from app.config import Settings
from app.main import create_app

LIVE_EXPOSURE_MS = 30.0  # the paper's range; the simulator renders each frame well within the period
LIVE_SCENE = "dof_target"  # static: cheap to render, and has a known truth


@pytest.fixture(scope="session")
def sim_calibration_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The simulator's calibration, made the way a first start makes it (and checked on the way).

    An instrument started on an empty data folder shows "calibrating", simulates board
    poses, calibrates, and stores ``calibrations/sim.json``; every other test reuses it.
    """
    from app.service.instrument import Instrument

    data = tmp_path_factory.mktemp("simcal")
    inst = Instrument(Settings(data_dir=data, viewer=False, autostart=False, sim_seed=0))
    try:
        inst.start()
        assert inst.state() == "calibrating"
        assert inst.status().to_dict()["calibration"] is None
        deadline = time.monotonic() + 900
        while inst.calibrations.creating and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not inst.calibrations.creating, "simulator calibration took more than 15 minutes"
        assert inst.calibration is not None, inst.status().to_dict()["last_error"]
        assert (summary := inst.calibrations.summary()) is not None and summary.name == "sim"
    finally:
        inst.close()
    path = data / "calibrations" / "sim.json"
    assert path.is_file()
    return path


def live_settings(tmp_path: Path, calibration_file: Path | None, **overrides: Any) -> Settings:
    values: dict[str, Any] = {
        "data_dir": tmp_path / "data", "calibration_file": calibration_file, "viewer": False,
        "sim_seed": 1, "exposure_ms": LIVE_EXPOSURE_MS, "sim_scene": LIVE_SCENE,
    }
    values.update(overrides)
    return Settings(**values)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path) -> Iterator[TestClient]:
    """One running app shared by a module's tests (they restore what they change)."""
    settings = live_settings(tmp_path_factory.mktemp("live"), sim_calibration_file)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda st: st["results_published"] >= 1, 120)
        yield client


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
