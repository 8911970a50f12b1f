"""The simulator's calibration, made once per test run (a pytest plugin: tests/conftest.py).

Every test that needs a stored simulator calibration (the API, outputs, service, browser and
start-progress tests) asks for ``sim_calibration_file``. It lives here, not in one package's
conftest, because a session fixture imported into another test module becomes a second
fixture there and calibrates again (minutes on a busy machine).

One run may be several processes: the pytest-xdist workers, and ``make test``'s second
invocation for the serial tests. They share one calibration: the first process to take the
lock on the shared folder makes it, the others wait on the lock and reuse the file. The
folder is ``FRINGESCOPE_TEST_SHARED_DIR`` when set (the Makefile makes one for both
invocations and removes it after), else the run's pytest temporary root under xdist (shared
by its workers), else this process's own temporary folder.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import time
from pathlib import Path

import pytest

from app.config import Settings

SHARED_DIR_ENV = "FRINGESCOPE_TEST_SHARED_DIR"


def shared_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder the processes of one test run share (see the module docstring)."""
    given = os.environ.get(SHARED_DIR_ENV)
    if given:
        path = Path(given)
    elif os.environ.get("PYTEST_XDIST_WORKER"):  # its basetemp is <run root>/popen-gwN
        path = tmp_path_factory.getbasetemp().parent / "shared"
    else:
        path = tmp_path_factory.getbasetemp() / "shared"
    path.mkdir(parents=True, exist_ok=True)
    return path


def make_sim_calibration(data: Path) -> Path:
    """Start an instrument on the empty folder ``data`` as a first start does and wait for the
    simulator's calibration (checked on the way); returns ``data/calibrations/sim.json``.

    An instrument started on an empty data folder shows "calibrating", simulates board
    poses, calibrates, and stores ``calibrations/sim.json``.
    """
    from app.service.instrument import Instrument

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


def compile_live_kernels(data: Path, calibration_file: Path) -> None:
    """Run the live instrument with ``calibration_file`` until its first depth map: the
    kernels of the live path are compiled into numba's disk cache (NUMBA_CACHE_DIR)."""
    from app.service.instrument import Instrument

    inst = Instrument(Settings(data_dir=data, calibration_file=calibration_file, viewer=False,
                               sim_seed=1, sim_scene="dof_target"))
    try:
        inst.start()
        deadline = time.monotonic() + 900
        while inst.status().to_dict()["results_published"] < 1:
            assert time.monotonic() < deadline, "no live depth map within 15 minutes"
            time.sleep(0.5)
    finally:
        inst.close()


@pytest.fixture(scope="session")
def sim_calibration_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The simulator's calibration, made the way a first start makes it, once per test run.

    The calibration is made in ``<shared>/simcal-data`` under an exclusive lock; a process
    that finds the file there (written atomically by the service) reuses it. Under the same
    lock the first process runs the live instrument to its first depth map once: with a
    fresh numba cache two workers otherwise compiled the same kernels side by side while
    their live tests' first-result timeouts ran.
    """
    shared = shared_dir(tmp_path_factory)
    data = shared / "simcal-data"
    path = data / "calibrations" / "sim.json"
    compiled = shared / "live-kernels-compiled"
    with open(shared / "simcal.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not path.is_file():
            if data.exists():  # a process that held the lock died mid-way: start afresh
                shutil.rmtree(data)
            data.mkdir()
            make_sim_calibration(data)
        if not compiled.exists():
            warm = shared / "live-kernels-data"
            shutil.rmtree(warm, ignore_errors=True)
            compile_live_kernels(warm, path)
            shutil.rmtree(warm, ignore_errors=True)
            compiled.touch()
        return path
