"""Shared test setup: numba on 2 cores must not spin OpenMP threads; memory per test on request."""

import os

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

pytest_plugins = ["tests.helpers.rss"]  # FRINGESCOPE_TEST_RSS=FILE logs each test's RSS
