"""Fits shared by the calibration tests: a calibration solve costs ~30 s of CPU, so a fit two
modules make of the same observations is made once for the package and read by both."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from app.calib import fit_observations
from app.calib.fitting import CalibrationReport
from tests.helpers.calib_fits import standard_noisy_observations
from tests.helpers.calib_rig import Rig


@pytest.fixture(scope="package")
def standard_noisy_fit() -> Iterator[tuple[Rig, CalibrationReport]]:
    """The analytic rig and its default calibration (dense, refined, model chosen) of
    :func:`tests.helpers.calib_fits.standard_noisy_observations`: read-only, shared by
    test_fit and test_refine_check; dropped when the package's tests end."""
    rig = Rig()
    report = fit_observations(
        standard_noisy_observations(rig), (rig.width, rig.height), rig.schedule
    )
    yield rig, report
    del report
