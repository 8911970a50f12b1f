from __future__ import annotations

import numpy as np
import pytest

from app.devices.base import Frame
from app.service.framesets import GroupWindow, SetAssembler

N = 16


def frames(indices, patterns, exposure_ms=20.0, led="green"):
    return [
        Frame(np.full((2, 3), p, np.uint8), index=i, timestamp=0.01 * i, pattern_index=p,
              exposure_ms=exposure_ms, led=led)
        for i, p in zip(indices, patterns, strict=True)
    ]


def feed_all(asm, fs):
    return [s for f in fs if (s := asm.feed(f, 0.0)) is not None]


def test_whole_sets_in_pattern_order():
    asm = SetAssembler(N)
    out = feed_all(asm, frames(range(40), [i % N for i in range(40)]))
    assert len(out) == 2 and asm.completed == 2 and asm.incomplete == 0
    assert out[1].frame_indices == list(range(16, 32))
    stack = out[0].stack()
    assert stack.shape == (16, 2, 3) and list(stack[:, 0, 0]) == list(range(16))


def test_starting_mid_sequence_waits_for_pattern_zero():
    asm = SetAssembler(N)
    out = feed_all(asm, frames(range(5, 37), [i % N for i in range(5, 37)]))
    assert len(out) == 1 and out[0].frame_indices == list(range(16, 32))
    assert asm.incomplete == 0 and asm.skipped_frames == 11


@pytest.mark.parametrize(
    "patterns, indices",
    [
        ([p for p in range(N) if p != 7], [i for i in range(N) if i != 7]),  # dropped frame
        (list(range(8)) + [7] + list(range(8, N)), list(range(N + 1))),  # duplicated pattern
        (list(range(5)) + [6, 5] + list(range(7, N)), list(range(N))),  # out of order
        (list(range(N)), list(range(8)) + [9] + list(range(10, N + 2))[: N - 9]),  # counter gap only
    ],
)
def test_broken_sets_are_discarded_and_counted(patterns, indices):
    asm = SetAssembler(N)
    fs = frames(indices[: len(patterns)], patterns[: len(indices)])
    # Follow with one clean set: it must still be found.
    start = fs[-1].index + 1
    fs += frames(range(start, start + N), range(N))
    out = feed_all(asm, fs)
    assert asm.incomplete == 1
    assert len(out) == 1 and out[0].frame_indices == list(range(start, start + N))


def test_settings_change_inside_a_set_discards_it():
    asm = SetAssembler(N)
    fs = frames(range(8), range(8), exposure_ms=20.0) + frames(range(8, 16), range(8, 16), exposure_ms=30.0)
    fs += frames(range(16, 32), range(16), exposure_ms=30.0)
    out = feed_all(asm, fs)
    assert asm.mixed == 1 and asm.incomplete == 0
    assert len(out) == 1 and out[0].exposure_ms == 30.0


def test_abort_counts_only_a_started_set():
    asm = SetAssembler(N)
    asm.abort()
    assert asm.incomplete == 0
    feed_all(asm, frames(range(3), range(3)))
    asm.abort()
    assert asm.incomplete == 1 and asm.in_progress == 0


def test_rolling_set_after_every_completed_group_from_the_newest_groups():
    win = GroupWindow(4, 4)
    out = [(i, s) for i, f in enumerate(frames(range(40), [i % N for i in range(40)]))
           if (s := win.feed(f, 0.0)) is not None]
    # the first set once all four groups exist (frame 15), then one per group of 4 frames
    assert [i for i, _ in out] == [15, 19, 23, 27, 31, 35, 39]
    _, s = out[1]  # after frame 19: groups 1..3 of frames 4..15 and the new group 0 (frames 16..19)
    assert s.mode == "rolling"
    assert [f.pattern_index for f in s.frames] == list(range(N))
    assert s.frame_indices == list(range(16, 20)) + list(range(4, 16))


def test_rolling_sets_skip_a_drop_until_every_group_is_newer_than_it():
    win = GroupWindow(4, 4)
    idx = [i for i in range(48) if i != 21]  # frame 21 (group 1, step 1) lost
    out = [f.index for f in frames(idx, [i % N for i in idx]) if win.feed(f, 0.0) is not None]
    # group 1 of frames 20..23 never completes; the sets 23..35 would mix in the stale group 1
    # of frames 4..7 (a counter gap), so the next set is after group 1 of frames 36..39
    assert out == [15, 19, 39, 43, 47]


def test_rolling_sets_do_not_mix_settings():
    win = GroupWindow(4, 4)
    fs = frames(range(20), [i % N for i in range(20)], exposure_ms=20.0)
    fs += frames(range(20, 40), [i % N for i in range(20, 40)], exposure_ms=30.0)
    out = [s for f in fs if (s := win.feed(f, 0.0)) is not None]
    assert [max(s.frame_indices) for s in out] == [15, 19, 35, 39]  # 23..31 mix 20 and 30 ms
    assert [s.exposure_ms for s in out] == [20.0, 20.0, 30.0, 30.0]


def test_invalid_sizes():
    with pytest.raises(ValueError, match="n_frames"):
        SetAssembler(0)
    with pytest.raises(ValueError, match="n_groups"):
        GroupWindow(0, 4)
    with pytest.raises(ValueError, match="steps"):
        GroupWindow(4, 0)
