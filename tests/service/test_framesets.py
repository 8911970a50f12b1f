from __future__ import annotations

import numpy as np
import pytest

from app.devices.base import Frame
from app.service.framesets import GroupWindow, SetAssembler, depth_group_of

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
        # counter gap only
        (list(range(N)), list(range(8)) + [9] + list(range(10, N + 2))[: N - 9]),
    ],
)
def test_a_broken_sequence_is_never_reconstructed_and_is_counted(patterns, indices):
    # one group of 16: a broken frame costs the whole set (the old whole-set rule)
    asm = SetAssembler(N)
    fs = frames(indices[: len(patterns)], patterns[: len(indices)])
    # Follow with one clean set: it must still be found.
    start = fs[-1].index + 1
    fs += frames(range(start, start + N), range(N))
    out = feed_all(asm, fs)
    assert asm.incomplete >= 1 and asm.completed == 1
    assert len(out) == 1 and out[0].frame_indices == list(range(start, start + N))


def test_a_dropped_frame_costs_only_its_group():
    asm = SetAssembler(N, 4)
    idx = [i for i in range(48) if i != 21]  # frame 21 (cycle 1, group 1) lost
    out = feed_all(asm, frames(idx, [i % N for i in idx]))
    # cycle 1 takes group 1 from cycle 0 (frames 4..7) and keeps the rest of its own
    assert [s.frame_indices for s in out] == [
        list(range(16)),
        list(range(16, 20)) + list(range(4, 8)) + list(range(24, 32)),
        list(range(32, 48)),
    ]
    assert [f.pattern_index for f in out[1].frames] == list(range(N))
    assert asm.completed == 3 and asm.patched == 1 and asm.groups_lost == 1 and asm.incomplete == 0


def test_a_lost_last_group_is_noticed_at_the_next_cycle():
    asm = SetAssembler(N, 4)
    idx = [i for i in range(48) if i != 30]  # frame 30 (cycle 1, group 3) lost
    got = [(f.index, s.frame_indices) for f in frames(idx, [i % N for i in idx])
           if (s := asm.feed(f, 0.0)) is not None]
    # the set of cycle 1 (its group 3 from cycle 0) is emitted when frame 32 shows a new cycle
    assert got[1] == (32, list(range(16, 28)) + list(range(12, 16)))
    assert len(got) == 3 and asm.patched == 1


def test_stand_in_groups_are_at_most_three_cycles_old():
    asm = SetAssembler(N, 4)
    # group 1 (patterns 4..7) lost in cycles 1..3: cycles 1 and 2 borrow it from cycle 0,
    # cycle 3 cannot (cycle 0 is more than 3 cycles of frames back)
    idx = [i for i in range(80) if not (i % N == 5 and 1 <= i // N <= 3)]
    out = feed_all(asm, frames(idx, [i % N for i in idx]))
    assert [max(s.frame_indices) for s in out] == [15, 31, 47, 79]
    assert asm.incomplete == 1 and asm.patched == 2


def test_ten_percent_random_drops_keep_most_of_the_depth_rate():
    # the target on the grouping alone: >= 0.7 x the drop-free set rate
    rng = np.random.default_rng(5)
    n = 16 * 2000
    idx = [i for i in range(n) if rng.random() >= 0.10]
    for steps, floor in ((4, 0.7), (N, 0.0)):
        asm = SetAssembler(N, steps)
        out = feed_all(asm, frames(idx, [i % N for i in idx]))
        ratio = len(out) / (n // N)
        for s in out:  # every group gap-free and in pattern order
            assert [f.pattern_index for f in s.frames] == list(range(N))
            for g in range(0, N, 4):
                grp = s.frame_indices[g: g + 4]
                assert grp == list(range(grp[0], grp[0] + 4))
            assert max(s.frame_indices) - min(s.frame_indices) < 3 * N
        assert ratio >= floor, (steps, ratio)
        if steps == N:
            assert ratio < 0.25  # the whole-set rule: 0.9^16 = 0.19


def test_settings_change_inside_a_set_discards_it():
    asm = SetAssembler(N)
    fs = frames(range(8), range(8), exposure_ms=20.0) + frames(
        range(8, 16), range(8, 16), exposure_ms=30.0
    )
    fs += frames(range(16, 32), range(16), exposure_ms=30.0)
    out = feed_all(asm, fs)
    assert asm.mixed == 1 and asm.incomplete == 0
    assert len(out) == 1 and out[0].exposure_ms == 30.0


def test_after_an_abort_a_camera_counting_from_zero_again_gives_sets():
    asm = SetAssembler(N, 4)
    assert len(feed_all(asm, frames(range(96, 128), [i % N for i in range(96, 128)]))) == 2
    asm.abort()  # the devices were re-opened: the frame counter restarts
    out = feed_all(asm, frames(range(32), [i % N for i in range(32)]))
    assert [s.frame_indices for s in out] == [list(range(16)), list(range(16, 32))]


def test_abort_in_a_cycle_joined_mid_sequence_is_no_loss():
    asm = SetAssembler(N, 4)
    feed_all(asm, frames(range(5, 9), range(5, 9)))  # started mid-cycle: not a cycle of ours
    asm.abort()
    assert asm.incomplete == 0


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


def test_rolling_sets_carry_on_past_a_drop():
    win = GroupWindow(4, 4)
    idx = [i for i in range(48) if i != 21]  # frame 21 (group 1, step 1) lost
    got = [(f.index, s) for f in frames(idx, [i % N for i in idx])
           if (s := win.feed(f, 0.0)) is not None]
    # no set is lost: frame 5 (the same phase, one cycle older) stands in for frame 21
    assert [i for i, _ in got] == [15, 19, 23, 27, 31, 35, 39, 43, 47]
    assert got[2][1].frame_indices == [16, 17, 18, 19, 20, 5, 22, 23, *range(8, 16)]
    assert got[3][1].frame_indices == [16, 17, 18, 19, 20, 5, 22, 23, *range(24, 28),
                                       12, 13, 14, 15]
    assert got[6][1].frame_indices == list(range(32, 40)) + list(range(24, 32))  # 37 replaced 5
    assert [f.pattern_index for f in got[2][1].frames] == list(range(N))
    assert win.completed == 9 and win.patched == 4 and win.incomplete == 0


def test_a_lost_last_phase_ends_its_group_at_the_next_frame():
    win = GroupWindow(4, 4)
    idx = [i for i in range(32) if i != 23]  # the last phase of group 1 (frames 20..23) lost
    got = [(f.index, s) for f in frames(idx, [i % N for i in idx])
           if (s := win.feed(f, 0.0)) is not None]
    assert [i for i, _ in got] == [15, 19, 24, 27, 31]  # group 1's set comes with frame 24
    assert got[2][1].frame_indices == [16, 17, 18, 19, 20, 21, 22, 7, *range(8, 16)]


def test_a_stand_in_is_at_most_one_cycle_old():
    win = GroupWindow(4, 4)
    idx = [i for i in range(64) if i not in (21, 37)]  # phase 5 lost in two cycles running
    out = [f.index for f in frames(idx, [i % N for i in idx]) if win.feed(f, 0.0) is not None]
    # frame 5 stands in for 21 (sets at 23 … 35); from 39 it would stand in for 37, two cycles
    # on: no set until frame 53 brings that phase back (group 1 ends with frame 55)
    assert out == [15, 19, 23, 27, 31, 35, 55, 59, 63]
    assert win.incomplete == 4 and win.patched == 4


def test_the_depth_group_takes_no_stand_in():
    win = GroupWindow(4, 4, depth_group=3)  # the finest frequency last, as in paper-16
    idx = [i for i in range(48) if i != 29]  # group 3 (frames 28..31) loses a frame
    got = [(f.index, s) for f in frames(idx, [i % N for i in idx])
           if (s := win.feed(f, 0.0)) is not None]
    # at 31 the set would repeat the one of 27 (group 3 keeps its whole copy 12..15): none
    assert [i for i, _ in got] == [15, 19, 23, 27, 35, 39, 43, 47]
    assert got[4][1].frame_indices == [*range(32, 36), *range(20, 28), 12, 13, 14, 15]
    assert win.incomplete == 1 and win.patched == 0
    # a coarser group's lost frame is stood in for, as without a depth group
    win = GroupWindow(4, 4, depth_group=3)
    idx = [i for i in range(32) if i != 21]
    got = [(f.index, s) for f in frames(idx, [i % N for i in idx])
           if (s := win.feed(f, 0.0)) is not None]
    assert [i for i, _ in got] == [15, 19, 23, 27, 31]
    assert got[2][1].frame_indices[4:8] == [20, 5, 22, 23] and win.patched == 3


def test_depth_group_of_is_the_finest_frequency():
    assert depth_group_of((1, 4, 12, 36)) == 3
    assert depth_group_of((36.0, 6.0, 1.0)) == 0
    with pytest.raises(ValueError, match="frequencies"):
        depth_group_of(())
    with pytest.raises(ValueError, match="depth_group"):
        GroupWindow(4, 4, depth_group=4)


def test_rolling_sets_span_at_most_max_span_cycles():
    win = GroupWindow(4, 4, max_span_cycles=1)
    idx = [i for i in range(48) if i != 21]
    out = [f.index for f in frames(idx, [i % N for i in idx]) if win.feed(f, 0.0) is not None]
    assert out == [15, 19, 39, 43, 47]  # one cycle at most: the stale group waits for a new one


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
    with pytest.raises(ValueError, match="steps"):
        SetAssembler(16, 5)
    with pytest.raises(ValueError, match="max_span_cycles"):
        SetAssembler(16, 4, max_span_cycles=0)
    with pytest.raises(ValueError, match="n_groups"):
        GroupWindow(0, 4)
    with pytest.raises(ValueError, match="steps"):
        GroupWindow(4, 0)
