"""Shared test setup: numba on 2 cores must not spin OpenMP threads."""

import os

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
