"""Shared test setup: numba and OpenBLAS configured as the CLI configures them (no spinning OpenMP
or BLAS threads on 2 cores, 512-bit vectors where the CPU has them: app/core/jit.py) before any
test imports numpy or numba; memory
released after each module (tests/helpers/release.py) and logged per test on request
(tests/helpers/rss.py)."""

from app.core.jit import configure_numerics

configure_numerics()

pytest_plugins = [
    "tests.helpers.release",  # after each module: FastAPI's endpoint caches, cycles, heap
    "tests.helpers.rss",  # FRINGESCOPE_TEST_RSS=FILE logs each test's resident set
    "tests.helpers.sim_calibration",  # sim_calibration_file: made once per session
]
