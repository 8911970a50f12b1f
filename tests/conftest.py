"""Shared test setup: numba configured as the CLI configures it (no spinning OpenMP threads on 2
cores, 512-bit vectors where the CPU has them: app/core/jit.py) before any test imports it; memory
released after each module (tests/helpers/release.py) and logged per test on request
(tests/helpers/rss.py)."""

import tests.helpers.blas_threads  # noqa: F401  (first: one BLAS thread, before numpy loads)
from app.core.jit import configure_numba

configure_numba()

pytest_plugins = [
    "tests.helpers.release",  # after each module: FastAPI's endpoint caches, cycles, heap
    "tests.helpers.rss",  # FRINGESCOPE_TEST_RSS=FILE logs each test's resident set
    "tests.helpers.sim_calibration",  # sim_calibration_file: made once per session
]
