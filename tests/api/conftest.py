"""Live-app fixtures: the real app with its lifespan on the simulator.

The calibration is made once per session the way a user would make it (simulated board
poses → ``calibrate_folder``; ``sim_calibration_file`` in tests/helpers/sim_calibration.py)
and handed to every app through ``calibration_file``, so no app spends its start-up
calibrating.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

from app.main import create_app
from tests.helpers.live_app import live_settings, wait_for


@pytest.fixture(scope="module")
def live(
    tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path
) -> Iterator[TestClient]:
    """One running app shared by a module's tests (they restore what they change)."""
    settings = live_settings(tmp_path_factory.mktemp("live"), sim_calibration_file)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda st: st["results_published"] >= 1, 120)
        yield client
