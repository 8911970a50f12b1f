"""Projector image generation for a fringe pattern schedule (Le et al. 2018, Sec. 2)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from app.core.schedule import ORIENTATIONS, PatternSchedule

__all__ = ["ORIENTATIONS", "PatternSchedule", "fringe_profile", "generate_patterns"]


def fringe_profile(
    schedule: PatternSchedule, freq_index: int, shift_index: int, *,
    columns: npt.ArrayLike | None = None
) -> npt.NDArray[np.float64]:
    """Relative intensity 0.5 + 0.5 cos(2π k x / L + 2π n / N) along the fringe axis.

    Args:
        columns: coordinates x along the fringe axis (projector columns for vertical
            fringes, rows for horizontal; float, pixels); default every pixel of the axis.
            L = ``schedule.axis_length``.

    Returns:
        float64 array of the shape of ``columns``, values in [0, 1].
    """
    length = schedule.axis_length
    x = np.arange(length, dtype=np.float64) if columns is None else np.asarray(columns, np.float64)
    k = schedule.frequencies[freq_index]
    delta = 2.0 * math.pi * shift_index / schedule.steps
    return 0.5 + 0.5 * np.cos(2.0 * math.pi * k * x / length + delta)


def generate_patterns(schedule: PatternSchedule) -> npt.NDArray[np.uint8]:
    """Projector images for every frame of ``schedule``.

    Returns:
        uint8 array (F, height, width), F = ``schedule.n_frames``, full range 0–255,
        frequency-major and shift-minor.
    """
    out = np.empty((schedule.n_frames, schedule.height, schedule.width), np.uint8)
    for fi in range(len(schedule.frequencies)):
        for n in range(schedule.steps):
            line = np.rint(255.0 * fringe_profile(schedule, fi, n)).astype(np.uint8)
            horizontal = schedule.orientation == "horizontal"
            out[schedule.frame_index(fi, n)] = line[:, None] if horizontal else line[None, :]
    return out
