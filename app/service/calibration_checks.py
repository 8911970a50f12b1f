"""Checks a calibration passes before it goes live, and the watch on the live valid fraction.

A calibration file is the user's input: a corrupted one (a focal length of 0, a flipped sign, a
region of NaN, an uncertainty of a kilometre) parses fine and would silently give no depth, or
wrong depth. :func:`check_physical` refuses what cannot describe a real instrument;
:func:`dry_run_problem` refuses what would leave far fewer pixels valid on the newest frames than
the active calibration does; :class:`ValidFractionWatch` turns a collapse of the live valid
fraction after any change into a status warning.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration
from app.core.geometric import GeometricModel
from app.core.schedule import PatternSchedule, calibration_mismatch

#: a board's reprojection error above this many pixels means the camera model does not fit at all
MAX_REPROJECTION_PX = 50.0
#: the calibration error's correlation length cannot exceed the field of a laparoscope, mm
MAX_CORRELATION_MM = 1000.0
#: refused when the dry run leaves fewer valid pixels than this fraction of the active calibration's
MIN_VALID_RATIO = 0.5
#: below this valid fraction (of the active calibration) there is nothing to compare with
MIN_REFERENCE_FRACTION = 0.02
#: held-out error figures (mm) that must be finite, >= 0 and below the calibrated height span
HELD_OUT_MM = ("rms_mm", "max_mm", "noise_mm", "systematic_mm")


def check_physical(cal: Calibration, schedule: PatternSchedule) -> None:
    """Raise ``ValueError`` naming the field if ``cal`` cannot describe a real instrument.

    Args:
        cal: the calibration to check (already parsed: arrays have their shapes).
        schedule: the pattern schedule the live pipeline runs.

    Checks: positive focal lengths and a principal point inside the image; the camera above
    the reference plane; every model parameter finite; a supported region that is finite and
    non-empty; projector width and fringe count matching the pattern and the schedule;
    held-out and per-pose errors finite, >= 0 and within the calibrated height span.
    """
    _check_camera(cal)
    _check_model(cal)
    _check_pattern(cal, schedule)
    _check_uncertainties(cal)


def _check_camera(cal: Calibration) -> None:
    k = cal.camera_matrix
    fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    if not (fx > 0 and fy > 0):
        raise ValueError(f"camera_matrix: focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
    if not np.array_equal(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0.0:
        raise ValueError("camera_matrix: must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    w, h = cal.image_size
    if not (0.0 <= cx <= w and 0.0 <= cy <= h):
        raise ValueError(f"camera_matrix: principal point ({cx:g}, {cy:g}) lies outside the "
                         f"{w}x{h} image")
    if not cal.plane_offset_mm > 0.0:
        raise ValueError("reference_plane.offset_mm: the camera must be above the reference "
                         f"plane (> 0 mm), got {cal.plane_offset_mm:g}")
    lo, hi = cal.height_range_mm
    if hi >= cal.plane_offset_mm:
        raise ValueError(f"height_range_mm: the top {hi:g} mm reaches the camera "
                         f"({cal.plane_offset_mm:g} mm above the reference plane)")


def _numbers(value: Any, path: str) -> Iterator[tuple[str, float]]:
    """Every number inside a JSON-like ``value`` with its dotted path."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float, np.floating, np.integer)):
        yield path, float(value)
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _numbers(item, f"{path}.{key}")
    elif isinstance(value, (list, tuple, np.ndarray)):
        for item in value:
            yield from _numbers(item, path)


def _check_model(cal: Calibration) -> None:
    model = cal.model
    for path, x in _numbers(model.params(), "model"):
        if not math.isfinite(x):
            raise ValueError(f"{path}: must be finite, got {x}")
    region = model.region
    if region.phase_rad is not None:
        lo, hi = region.phase_rad
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError("model.supported_region.phase_rad: need finite lo < hi, "
                             f"got [{lo}, {hi}]")
    if region.height_grid_mm is not None:
        grid: npt.NDArray[np.float64] = np.asarray(region.height_grid_mm, np.float64)
        if np.isnan(grid).any():
            raise ValueError("model.supported_region.height_grid_mm: contains NaN")
        if not (grid[..., 0] <= grid[..., 1]).any():
            raise ValueError("model.supported_region.height_grid_mm: no cell "
                             "has data (empty region)")
    if not all(math.isfinite(x) for x in region.cell_px):
        raise ValueError("model.supported_region.cell_px: must be finite")
    if isinstance(model, GeometricModel) and model.focal_px <= 0.0:
        raise ValueError(f"model.focal_px: must be positive, got {model.focal_px:g}")


def _check_pattern(cal: Calibration, schedule: PatternSchedule) -> None:
    reason = calibration_mismatch(cal.pattern, schedule)
    if reason is not None:
        raise ValueError(f"pattern: {reason}")
    model = cal.model
    if isinstance(model, GeometricModel):
        axis = cal.pattern.axis_length
        finest = cal.pattern.frequencies[-1]
        if model.projector_width_px != axis:
            raise ValueError(f"model.projector_width_px: {model.projector_width_px} differs from "
                             f"the pattern's {axis} px")
        if model.fringes != finest:
            raise ValueError(f"model.fringes: {model.fringes} differs from the pattern's finest "
                             f"fringe count {finest}")


def _check_uncertainties(cal: Calibration) -> None:
    lo, hi = cal.height_range_mm
    span_mm = hi - lo
    for name, figures in cal.held_out.items():
        if not isinstance(figures, dict):
            raise ValueError(f"held_out.{name}: expected an object")
        for key in (*HELD_OUT_MM, "correlation_mm"):
            value = figures.get(key)
            if value is None:
                continue
            limit = MAX_CORRELATION_MM if key == "correlation_mm" else span_mm
            _bounded(f"held_out.{name}.{key}", value, limit)
    for i, pose in enumerate(cal.pose_residuals):
        if not isinstance(pose, dict):
            raise ValueError(f"pose_residuals[{i}]: expected an object")
        for key, limit in (("rms_mm", span_mm), ("reprojection_px", MAX_REPROJECTION_PX)):
            if pose.get(key) is not None:
                _bounded(f"pose_residuals[{i}].{key}", pose[key], limit)


def _bounded(path: str, value: Any, limit: float) -> None:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: not a number") from None
    if not (math.isfinite(x) and 0.0 <= x <= limit):
        raise ValueError(f"{path}: must be finite and within 0-{limit:.4g}, got {x:g}")


def dry_run_problem(candidate_fraction: float, active_fraction: float, active_name: str | None
                    ) -> str | None:
    """Why a candidate calibration must not replace the active one, or None.

    Args:
        candidate_fraction: valid fraction (0-1) of the newest frames with the candidate.
        active_fraction: valid fraction (0-1) of the same frames with the active calibration.
        active_name: the active calibration's name (for the message).
    """
    if not (0.0 <= candidate_fraction <= 1.0 and 0.0 <= active_fraction <= 1.0):
        raise ValueError("candidate_fraction, active_fraction: must be within 0-1")
    if active_fraction < MIN_REFERENCE_FRACTION:
        return None
    if candidate_fraction >= MIN_VALID_RATIO * active_fraction:
        return None
    return (f"dry run on the newest frames: {candidate_fraction:.1%} of pixels valid against "
            f"{active_fraction:.1%} with the active calibration {active_name!r} (refused below "
            f"{MIN_VALID_RATIO:.0%} of it; add force=true to activate anyway)")


class ValidFractionWatch:
    """The live valid fraction before the last change and since: a collapse is a warning.

    :meth:`observe` is fed the live results (by sequence number), :meth:`changed` marks a
    change (a calibration, the schedule, the exposure...), :meth:`warning` says whether the
    fraction since is below ``ratio`` times the level before.
    """

    def __init__(self, ratio: float = MIN_VALID_RATIO, window: int = 3) -> None:
        if not 0.0 < ratio < 1.0:
            raise ValueError(f"ratio: must be within 0-1, got {ratio}")
        if window < 1:
            raise ValueError(f"window: must be >= 1, got {window}")
        self.ratio = ratio
        self.level: float | None = None
        self.change: str | None = None
        self._recent: deque[float] = deque(maxlen=window)
        self._last_seq = -1

    @property
    def last_seq(self) -> int:
        """The sequence number of the newest result observed (-1: none yet)."""
        return self._last_seq

    def observe(self, seq: int, fraction: float) -> None:
        """One live result's valid fraction (0-1); a sequence number seen already is ignored."""
        if seq != self._last_seq:
            self._last_seq = seq
            self._recent.append(float(fraction))

    def changed(self, what: str) -> None:
        """A change happened: the level so far becomes the reference."""
        if self._recent:
            self.level = statistics.median(self._recent)
            self.change = what
        self._recent.clear()

    def warning(self) -> str | None:
        """A one-line warning while the fraction since the last change has collapsed, else None."""
        if self.level is None or self.level < MIN_REFERENCE_FRACTION or len(self._recent) < 2:
            return None
        now = statistics.median(self._recent)
        if now >= self.ratio * self.level:
            return None
        return (f"live valid fraction collapsed from {self.level:.1%} to {now:.1%} after "
                f"{self.change}: check the calibration and the scene")
