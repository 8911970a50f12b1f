"""app.service.measure.calibration_terms: the systematic part and its correlation length, or an old
file's RMS."""

from types import SimpleNamespace

import numpy as np

from app.service.measure import calibration_terms


def _cal(held):
    return SimpleNamespace(model=SimpleNamespace(name="geometric"), plane_normal=(0.0, 0.0, 1.0),
                           held_out={"geometric": held, "eq5": {"rms_mm": 9.0}})


def test_systematic_part_and_its_length():
    normal, s, length = calibration_terms(
        _cal({"rms_mm": 0.03, "noise_mm": 0.028, "systematic_mm": 0.01, "correlation_mm": 7.5})
    )
    assert np.array_equal(normal, [0.0, 0.0, 1.0]) and (s, length) == (0.01, 7.5)


def test_a_file_without_the_split_gives_its_rms_independent_between_points():
    assert calibration_terms(_cal({"rms_mm": 0.03}))[1:] == (0.03, 0.0)
    assert calibration_terms(_cal({"rms_mm": 0.03, "systematic_mm": None, "correlation_mm": None}))[
        1:
    ] == (0.03, 0.0)
    assert calibration_terms(_cal({}))[1:] == (0.0, 0.0)
    assert calibration_terms(None) == (None, 0.0, 0.0)
