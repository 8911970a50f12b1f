"""The instrument's limits: one range, one LED list, clear errors."""

from __future__ import annotations

import math

import pytest

from app.core.limits import EXPOSURE_RANGE_MS, LEDS, check_exposure_ms, check_led, full_scale


def test_exposure_range_inclusive():
    lo, hi = EXPOSURE_RANGE_MS
    assert check_exposure_ms(lo) == lo and check_exposure_ms(hi) == hi
    assert isinstance(check_exposure_ms(20), float)


@pytest.mark.parametrize("bad", [0.5, 100.5, math.nan, math.inf, "20", None])
def test_exposure_outside_named(bad):
    with pytest.raises(ValueError, match="exposure_ms"):
        check_exposure_ms(bad)


def test_led():
    assert [check_led(x) for x in LEDS] == list(LEDS)
    with pytest.raises(ValueError, match="led"):
        check_led("white")



def test_full_scale_is_the_largest_code_of_the_bit_depth() -> None:
    assert [full_scale(b) for b in (1, 8, 10, 12, 16)] == [1, 255, 1023, 4095, 65535]
    for bad in (0, 17, True, 8.0, "8"):
        with pytest.raises(ValueError, match="bit_depth"):
            full_scale(bad)  # type: ignore[arg-type]
