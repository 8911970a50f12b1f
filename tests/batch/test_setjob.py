"""The batch job's table figures: the same numbers as numpy's, by a cheaper path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.batch.setjob import median_float32


def _cases() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    sigma = rng.gamma(3.0, 0.05, 1384 * 1032).astype(np.float32)
    return {
        "camera-sized, even": sigma,
        "odd": sigma[:100_001].copy(),
        "one": np.array([0.25], np.float32),
        "two": np.array([0.1, 0.2], np.float32),  # the float32 mean of the middle pair
        "zeros and inf": np.array([0.0, np.inf, 3.0, 0.0, np.inf], np.float32),
        "ties": np.full(10, 0.125, np.float32),
        "negative values": rng.normal(0.0, 1.0, 1001).astype(np.float32),
        "negative zero": np.array([-0.0, 1.0, 2.0], np.float32),
    }


@pytest.mark.parametrize("name", list(_cases()))
def test_median_float32_is_numpys_median(name):
    values = _cases()[name]
    expected = float(np.median(values))
    got = median_float32(values.copy())
    assert got == expected, (got, expected)


def test_median_float32_nan_and_empty():
    assert math.isnan(median_float32(np.array([1.0, np.nan, 2.0], np.float32)))
    assert math.isnan(median_float32(np.array([1.0, -np.nan, 2.0], np.float32)))
    assert math.isnan(median_float32(np.empty(0, np.float32)))


def test_median_float32_names_its_argument():
    with pytest.raises(ValueError, match="^values"):
        median_float32(np.zeros(3))
