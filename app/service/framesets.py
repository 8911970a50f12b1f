"""Grouping camera frames into fringe sets (whole sets, or rolling sets per frequency group).

A set is reconstructed only if its frames carry pattern indices 0..F-1 in order, with
consecutive frame counters (a gap is a dropped frame) and one exposure/LED setting;
anything else is discarded and counted, never reconstructed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.devices.base import Frame


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


class SetAssembler:
    """Collects consecutive frames with pattern indices 0..F-1 into :class:`FrameSet` objects.

    Counters: ``completed`` sets emitted, ``incomplete`` sets discarded for a missing,
    duplicated or out-of-order frame, ``mixed`` sets discarded because a setting changed
    inside them, ``skipped_frames`` frames seen while waiting for the start of a set.
    """

    def __init__(self, n_frames: int) -> None:
        if n_frames < 1:
            raise ValueError(f"n_frames: must be >= 1, got {n_frames}")
        self.n_frames = n_frames
        self._pending: list[Frame] = []
        self.completed = 0
        self.incomplete = 0
        self.mixed = 0
        self.skipped_frames = 0

    @property
    def in_progress(self) -> int:
        """Frames collected toward the current set (0 at a set boundary)."""
        return len(self._pending)

    def abort(self) -> None:
        """Discard the set in progress (after a timeout or a fault), counting it."""
        if self._pending:
            self.incomplete += 1
            self._pending = []

    def feed(self, frame: Frame, received_s: float) -> FrameSet | None:
        """Add one frame; returns a complete set when ``frame`` finishes one."""
        p = frame.pattern_index
        if p == 0:
            self.abort()  # a new sequence starts: whatever was pending is short
            self._pending = [frame]
        elif not self._pending:
            self.skipped_frames += 1  # mid-sequence: wait for pattern 0
            return None
        else:
            prev = self._pending[-1]
            if p != prev.pattern_index + 1 or frame.index != prev.index + 1:
                self.abort()
                self.skipped_frames += 1
                return None
            self._pending.append(frame)
        if len(self._pending) < self.n_frames:
            return None
        frames, self._pending = tuple(self._pending), []
        if not _same_settings(frames):
            self.mixed += 1
            return None
        self.completed += 1
        return FrameSet(frames, received_s, "set")


class GroupWindow:
    """Rolling mode: a set after every completed frequency group, from the newest groups.

    A group is the ``steps`` frames of one frequency (pattern indices g·N … g·N + N − 1)
    with consecutive frame counters. When a group completes, the newest complete group of
    every frequency forms a set if together they are F frames with consecutive counters
    (no frame dropped in between, so no group is stale) and one exposure/LED setting. With
    the projector cycling through the schedule that is one new set per group: G times the
    whole-set rate, each set sharing G − 1 groups with the one before.
    """

    def __init__(self, n_groups: int, steps: int) -> None:
        if n_groups < 1:
            raise ValueError(f"n_groups: must be >= 1, got {n_groups}")
        if steps < 1:
            raise ValueError(f"steps: must be >= 1, got {steps}")
        self.n_groups = n_groups
        self.steps = steps
        self._groups: list[tuple[Frame, ...] | None] = [None] * n_groups
        self._pending: list[Frame] = []

    def clear(self) -> None:
        self._groups = [None] * self.n_groups
        self._pending = []

    def feed(self, frame: Frame, received_s: float) -> FrameSet | None:
        """Add one frame; returns a set when ``frame`` completes a group and the newest groups form one."""
        p = frame.pattern_index
        if p < 0 or p >= self.n_groups * self.steps:
            self._pending = []
            return None
        g, n = divmod(p, self.steps)
        if n == 0:
            self._pending = [frame]
        elif self._pending and p == self._pending[-1].pattern_index + 1 and frame.index == self._pending[-1].index + 1:
            self._pending.append(frame)
        else:
            self._pending = []
            return None
        if len(self._pending) < self.steps:
            return None
        self._groups[g], self._pending = tuple(self._pending), []
        if any(grp is None for grp in self._groups):
            return None
        frames = tuple(f for grp in self._groups if grp is not None for f in grp)
        idx = [f.index for f in frames]
        if max(idx) - min(idx) + 1 != len(frames) or len(set(idx)) != len(frames):
            return None
        if not _same_settings(frames):
            return None
        return FrameSet(frames, received_s, "rolling")
