"""The named schedule registry and the calibration carry-over rule."""

from __future__ import annotations

import pytest

from app.core.schedule import (
    DEFAULT_SCHEDULE,
    SCHEDULES,
    PatternSchedule,
    calibration_mismatch,
    schedule_by_name,
    schedule_name_of,
    schedule_names,
)


def test_default_is_the_paper_schedule_and_listed_first():
    assert DEFAULT_SCHEDULE == "paper-16" == schedule_names()[0]
    assert schedule_by_name("paper-16") == PatternSchedule() == PatternSchedule((1, 4, 12, 36), 4)
    assert schedule_by_name("paper-16").n_frames == 16


def test_a_reduced_schedule_of_at_most_nine_frames_exists():
    assert min(s.n_frames for s in SCHEDULES.values()) <= 9
    assert SCHEDULES["geometric-9"].n_frames == 9


def test_every_registered_schedule_keeps_the_finest_pattern():
    """So the default calibration carries over to every one of them."""
    for name, s in SCHEDULES.items():
        assert calibration_mismatch(SCHEDULES[DEFAULT_SCHEDULE], s) is None, name
        assert schedule_name_of(s) == name


def test_unknown_name_is_a_value_error_naming_schedule():
    with pytest.raises(ValueError, match="schedule: unknown name 'nope'"):
        schedule_by_name("nope")
    assert schedule_name_of(PatternSchedule((1, 3, 9), 4)) is None


@pytest.mark.parametrize("other, key", [
    (PatternSchedule((1, 4, 12), 4), "finest"),
    (PatternSchedule((1, 4, 12, 36), 4, orientation="horizontal"), "orientation"),
    (PatternSchedule((1, 4, 12, 36), 4, width=912, height=1140), "width"),
])
def test_calibration_does_not_carry_over_when_the_finest_phase_changes_meaning(other, key):
    reason = calibration_mismatch(PatternSchedule(), other)
    assert reason is not None and key in reason


def test_calibration_carries_over_across_steps_coarse_frequencies_and_unwrapping():
    assert calibration_mismatch(PatternSchedule(), PatternSchedule((1, 6, 36), 3)) is None
    assert (
        calibration_mismatch(
            PatternSchedule(), PatternSchedule((30, 35, 36), 5, unwrap="heterodyne")
        )
        is None
    )
