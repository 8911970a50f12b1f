"""Grouping camera frames into fringe sets (one per projector cycle, or rolling per group).

A set is built of frequency groups: the N phase-shifted frames of one frequency, carrying
pattern indices g·N … g·N + N − 1 in order with consecutive frame counters (a gap is a
dropped frame). A group with a missing, duplicated or out-of-order frame is discarded and
counted, never reconstructed; a set's groups share one exposure/LED setting and come from
at most ``MAX_SPAN_CYCLES`` projector cycles, so a dropped frame costs its group, not the
stream (an earlier copy of that group stands in; the motion test checks the groups).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.devices.base import Frame

#: a set's groups lie within this many projector cycles of frames: with 10 % of frames dropped at
#: random a group of 4 survives a cycle with p = 0.66, 1 - (1 - p)^3 = 0.96 of them in 3 cycles
MAX_SPAN_CYCLES = 3


@dataclass(frozen=True)
class FrameSet:
    """F frames in capture-set order (pattern index 0..F-1), ready to reconstruct.

    Attributes:
        frames: the F :class:`Frame` objects, ordered by pattern index.
        received_s: ``time.monotonic()`` when the newest frame arrived (latency origin).
        mode: ``"set"`` (a whole projected sequence) or ``"rolling"`` (the newest group of each
            frequency, emitted when a group completes).
    """

    frames: tuple[Frame, ...]
    received_s: float
    mode: str = "set"

    @property
    def exposure_ms(self) -> float:
        return self.frames[0].exposure_ms

    @property
    def led(self) -> str:
        return self.frames[0].led

    @property
    def frame_indices(self) -> list[int]:
        return [f.index for f in self.frames]

    @property
    def timestamps(self) -> list[float]:
        return [f.timestamp for f in self.frames]

    def stack(self) -> npt.NDArray[Any]:
        """(F, H, W) frames in capture-set order, the camera's dtype (uint8/uint16)."""
        return np.stack([f.data for f in self.frames])


def _same_settings(frames: list[Frame] | tuple[Frame, ...]) -> bool:
    first = frames[0]
    for f in frames[1:]:
        if f.led != first.led:
            return False
        a, b = f.exposure_ms, first.exposure_ms
        if not (a == b or (math.isnan(a) and math.isnan(b))):
            return False
    return True


def _follows(prev: Frame, frame: Frame) -> bool:
    """``frame`` is the next pattern and the next frame counter after ``prev``."""
    return frame.pattern_index == prev.pattern_index + 1 and frame.index == prev.index + 1


class SetAssembler:
    """Collects frames into :class:`FrameSet` objects, one per projector cycle, group by group.

    A group is the ``steps`` frames of one frequency (pattern indices g·N … g·N + N − 1) with
    consecutive frame counters. The newest complete group of every frequency is kept; at the
    end of each projector cycle (its last group completes, or a frame of the next cycle
    arrives) those groups form a set if they span at most ``max_span_cycles`` cycles of
    frames and share one exposure/LED setting. Without drops that is the cycle just seen; a
    dropped frame costs only its group, which an earlier cycle's copy stands in for (the
    motion test then checks the groups against each other, as in rolling mode). With
    ``steps`` None the whole cycle is one group: a dropped frame costs the whole set.

    Counters: ``completed`` sets emitted, ``patched`` of them with a group from an earlier
    cycle, ``incomplete`` cycles that ended without a set, ``groups_lost`` groups discarded
    for a missing, duplicated or out-of-order frame, ``mixed`` groups discarded because the
    setting changed after them, ``skipped_frames`` frames in no complete group.
    """

    def __init__(self, n_frames: int, steps: int | None = None, *,
                 max_span_cycles: int = MAX_SPAN_CYCLES) -> None:
        if n_frames < 1:
            raise ValueError(f"n_frames: must be >= 1, got {n_frames}")
        steps = n_frames if steps is None else steps
        if steps < 1 or n_frames % steps:
            raise ValueError(f"steps: must divide n_frames = {n_frames}, got {steps}")
        if max_span_cycles < 1:
            raise ValueError(f"max_span_cycles: must be >= 1, got {max_span_cycles}")
        self.n_frames = n_frames
        self.steps = steps
        self.n_groups = n_frames // steps
        self.max_span_frames = max_span_cycles * n_frames
        self._groups: list[tuple[Frame, ...] | None] = [None] * self.n_groups
        self._pending: list[Frame] = []  # the group in progress
        self._cycle_frames = 0  # frames seen in the current cycle
        self._fresh = False  # a group completed in the current cycle
        self._counted = False  # the current cycle counts as incomplete if it ends without a set
        self._synced = False  # a cycle boundary was seen since the start (or the last abort)
        self._mixed_in_cycle = False  # groups were discarded for a setting change in this cycle
        self._last: Frame | None = None
        self._emitted_newest = -1  # newest frame counter of the last set emitted
        self.completed = 0
        self.patched = 0
        self.incomplete = 0
        self.groups_lost = 0
        self.mixed = 0
        self.skipped_frames = 0

    @property
    def in_progress(self) -> int:
        """Frames seen in the current projector cycle (0 at a cycle boundary)."""
        return self._cycle_frames

    def abort(self) -> None:
        """Forget everything held (after a timeout, fault or restart), counting a started cycle."""
        if self._cycle_frames and self._counted:
            self.incomplete += 1
        if self._pending:
            self.groups_lost += 1
            self.skipped_frames += len(self._pending)
        self._groups = [None] * self.n_groups
        self._pending = []
        self._cycle_frames = 0
        self._fresh = False
        self._synced = False
        self._last = None
        self._emitted_newest = -1  # a restarted camera may count from 0 again

    def feed(self, frame: Frame, received_s: float) -> FrameSet | None:
        """Add one frame; returns a set when ``frame`` ends a projector cycle that yields one."""
        p = frame.pattern_index
        if not 0 <= p < self.n_frames:
            self._lose_pending()
            self.skipped_frames += 1
            return None
        out = None
        last = self._last
        if last is not None and (p <= last.pattern_index
                                 or frame.index - last.index > p - last.pattern_index):
            out = self._end_cycle(received_s)  # a new cycle began without the old one's last group
        self._last = frame
        if self._cycle_frames == 0:  # a partial first cycle (started mid-sequence) is no loss
            self._counted = self._synced or p == 0
        self._cycle_frames += 1
        g, n = divmod(p, self.steps)
        if n == 0:
            self._lose_pending()
            self._pending = [frame]
        elif self._pending and _follows(self._pending[-1], frame):
            self._pending.append(frame)
        else:
            self._lose_pending()
            self.skipped_frames += 1
            return out
        if len(self._pending) < self.steps:
            return out
        group, self._pending = tuple(self._pending), []
        if not _same_settings(group):  # the setting changed inside the group
            self.mixed += 1
            self._mixed_in_cycle = True
            self.skipped_frames += len(group)
            return out
        self._store(g, group)
        if g == self.n_groups - 1:
            done = self._end_cycle(received_s)
            out = done if done is not None else out
        return out

    def _lose_pending(self) -> None:
        if self._pending:
            self.groups_lost += 1
            self.skipped_frames += len(self._pending)
            self._pending = []

    def _store(self, g: int, group: tuple[Frame, ...]) -> None:
        for i, old in enumerate(self._groups):  # older groups of another setting can never join it
            if old is not None and i != g and not _same_settings((group[0], old[0])):
                self._groups[i] = None
                if not self._mixed_in_cycle:
                    self.mixed += 1
                self._mixed_in_cycle = True
        self._groups[g] = group
        self._fresh = True

    def _end_cycle(self, received_s: float) -> FrameSet | None:
        fresh, self._fresh = self._fresh, False
        started, self._cycle_frames = self._cycle_frames, 0
        counted = self._counted and not self._mixed_in_cycle  # a setting change is counted as mixed
        self._mixed_in_cycle = False
        self._synced = True
        self._last = None
        self._lose_pending()
        if not started:
            return None
        groups = self._groups
        if not fresh or any(grp is None for grp in groups):
            self.incomplete += int(counted)
            return None
        frames = tuple(f for grp in groups if grp is not None for f in grp)
        idx = [f.index for f in frames]
        newest = max(idx)
        if newest - min(idx) + 1 > self.max_span_frames or newest <= self._emitted_newest:
            self.incomplete += int(counted)  # a stand-in too old: the scene may have moved far
            return None
        self._emitted_newest = newest
        self.completed += 1
        if idx != list(range(idx[0], idx[0] + self.n_frames)):  # not one gap-free cycle
            self.patched += 1
        return FrameSet(frames, received_s, "set")


def depth_group_of(frequencies: tuple[float, ...] | list[float]) -> int:
    """The group (capture-set order) of the finest frequency: its phase gives the live depth."""
    if not frequencies:
        raise ValueError("frequencies: at least one needed")
    return max(range(len(frequencies)), key=lambda g: frequencies[g])


class GroupWindow:
    """Rolling mode: a set after every frequency group, from the newest frame of every pattern.

    The newest frame of each pattern index is kept. When a group ends (its last phase
    arrives, or a frame of another group does) the newest frames of every pattern form a
    set if each group's frames lie within one projector cycle of that group's newest (a
    dropped frame leaves its phase's previous frame standing in, one cycle older at most),
    the whole set spans at most ``max_span_cycles`` cycles of frames and shares one
    exposure/LED setting. With the projector cycling through the schedule that is one new
    set per group: G times the whole-set rate, each set sharing G − 1 groups with the one
    before. The motion test checks the groups (and so the stand-ins) against each other.

    ``depth_group`` (the finest frequency's, whose phase is the depth) takes no stand-ins:
    a frame of an earlier cycle among its phases would put the scene's motion straight into
    the depth, where a coarser group's only moves its fringe order (which the engine's
    order test guards). That group is the newest gap-free copy of its N frames; a set that
    would repeat the last one (the depth group lost a frame, nothing else is new) is not
    made.

    Counters: ``completed`` sets emitted, ``patched`` of them with a stand-in frame from an
    earlier cycle, ``incomplete`` groups that ended without a set (once every pattern was seen).
    """

    def __init__(self, n_groups: int, steps: int, *, depth_group: int | None = None,
                 max_span_cycles: int = MAX_SPAN_CYCLES) -> None:
        if n_groups < 1:
            raise ValueError(f"n_groups: must be >= 1, got {n_groups}")
        if steps < 1:
            raise ValueError(f"steps: must be >= 1, got {steps}")
        if depth_group is not None and not 0 <= depth_group < n_groups:
            raise ValueError(f"depth_group: must be within 0..{n_groups - 1}, got {depth_group}")
        if max_span_cycles < 1:
            raise ValueError(f"max_span_cycles: must be >= 1, got {max_span_cycles}")
        self.n_groups = n_groups
        self.steps = steps
        self.depth_group = depth_group
        self.n_frames = n_groups * steps
        self.max_span_frames = max_span_cycles * self.n_frames
        self._latest: list[Frame | None] = [None] * self.n_frames
        self._whole: tuple[Frame, ...] | None = None  # the depth group's newest gap-free copy
        self._pending: list[Frame] = []  # the depth group in progress
        # the group in progress: (group, frame counter of its phase 0), and whether it has a set
        self._open: tuple[int, int] | None = None
        self._open_done = True
        self._emitted: list[int] = []  # frame counters of the last set made
        self.completed = 0
        self.patched = 0
        self.incomplete = 0

    def clear(self) -> None:
        """Forget every frame held (a mode, schedule or device change)."""
        self._latest = [None] * self.n_frames
        self._whole, self._pending = None, []
        self._open, self._open_done = None, True
        self._emitted = []

    def feed(self, frame: Frame, received_s: float) -> FrameSet | None:
        """Add one frame; a set when a group ends and the newest frames form one."""
        p = frame.pattern_index
        if p < 0 or p >= self.n_frames:
            self._pending = []
            return None
        g, n = divmod(p, self.steps)
        instance = (g, frame.index - n)
        out = None
        if self._open is not None and instance != self._open and not self._open_done:
            # the group in progress lost its last phase(s): it ends now, with stand-ins
            out = self._emit(received_s)
        if instance != self._open:
            self._open, self._open_done = instance, False
        self._latest[p] = frame
        if g == self.depth_group:
            self._collect_whole(frame, n)
        if n == self.steps - 1:
            self._open_done = True
            out = self._emit(received_s) or out
        return out

    def _collect_whole(self, frame: Frame, n: int) -> None:
        if n == 0:
            self._pending = [frame]
        elif self._pending and _follows(self._pending[-1], frame):
            self._pending.append(frame)
        else:
            self._pending = []
        if len(self._pending) == self.steps:
            self._whole, self._pending = tuple(self._pending), []

    def _emit(self, received_s: float) -> FrameSet | None:
        """The newest frames as a set, if each group's stand-ins are recent enough."""
        latest = list(self._latest)
        if self.depth_group is not None:
            lo = self.depth_group * self.steps
            latest[lo:lo + self.steps] = self._whole or [None] * self.steps
        frames = tuple(f for f in latest if f is not None)
        if len(frames) < self.n_frames:  # still filling (start-up, after a change): no loss
            return None
        idx = [f.index for f in frames]
        if idx == self._emitted:  # nothing new: the depth group lost a frame
            self.incomplete += 1
            return None
        if not self._fits(idx) or not _same_settings(frames):
            self.incomplete += 1
            return None
        self._emitted = idx
        self.completed += 1
        if any(self._stood_in(idx, h) for h in range(self.n_groups)):
            self.patched += 1
        return FrameSet(frames, received_s, "rolling")

    def _fits(self, idx: list[int]) -> bool:
        if max(idx) - min(idx) + 1 > self.max_span_frames or len(set(idx)) != len(idx):
            return False
        for h in range(self.n_groups):
            group = idx[h * self.steps:(h + 1) * self.steps]
            # the newest instance of the group starts at its newest frame minus that one's phase
            newest = max(range(self.steps), key=lambda k: group[k])
            start = group[newest] - newest
            if min(group) < start - self.n_frames:  # a stand-in more than one cycle old
                return False
        return True

    def _stood_in(self, idx: list[int], h: int) -> bool:
        group = idx[h * self.steps:(h + 1) * self.steps]
        return any(group[k + 1] != group[k] + 1 for k in range(self.steps - 1))
