"""The simulator's calibration, made once per test session (a pytest plugin: tests/conftest.py).

Every test that needs a stored simulator calibration (the API, outputs, service, browser and
start-progress tests) asks for ``sim_calibration_file``. It lives here, not in one package's
conftest, because a session fixture imported into another test module becomes a second
fixture there and calibrates again (minutes on a busy machine).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from app.config import Settings


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
