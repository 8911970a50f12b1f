"""Browser-test fixtures.

``sim_calibration_file`` is the suite's session fixture (simulated board poses →
calibration, minutes on a busy machine); ``FRINGESCOPE_TEST_SIM_CALIBRATION`` may name
an existing simulator calibration file to skip making one.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.helpers.dashboard import page, server  # noqa: F401  (per-module fixtures: the app, one page)


@pytest.fixture(scope="session")
def browser_calibration_file(request: pytest.FixtureRequest) -> Path:
    given = os.environ.get("FRINGESCOPE_TEST_SIM_CALIBRATION")
    if given and Path(given).is_file():
        return Path(given)
    return Path(request.getfixturevalue("sim_calibration_file"))
