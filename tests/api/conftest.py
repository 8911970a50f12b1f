"""Live-app fixtures: the real app with its lifespan on the simulator.

The calibration is made once per session the way a user would make it (simulated board
poses → ``calibrate_folder``) and handed to every app through ``calibration_file``, so
no app spends its start-up calibrating.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

from app.config import Settings
from app.main import create_app
from tests.helpers.live_app import live_settings, wait_for


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


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path) -> Iterator[TestClient]:
    """One running app shared by a module's tests (they restore what they change)."""
    settings = live_settings(tmp_path_factory.mktemp("live"), sim_calibration_file)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda st: st["results_published"] >= 1, 120)
        yield client
