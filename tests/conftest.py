"""Shared test setup: numba on 2 cores must not spin OpenMP threads; memory released after each
module (tests/helpers/release.py) and logged per test on request (tests/helpers/rss.py)."""

import os

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

pytest_plugins = [
    "tests.helpers.release",  # after each module: FastAPI's endpoint caches, cycles, heap
    "tests.helpers.rss",  # FRINGESCOPE_TEST_RSS=FILE logs each test's resident set
    "tests.helpers.sim_calibration",  # sim_calibration_file: made once per session
]
