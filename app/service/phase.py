"""Calibration-free decoding of a capture set (``fringescope phase`` and ``POST /api/phase``)."""

from __future__ import annotations

from app.capture.captureset import CaptureSet
from app.core.errors import InvalidRequest
from app.recon import compute_phase
from app.recon.reconstructor import PhaseResult


def decode_capture(capture: CaptureSet) -> PhaseResult:
    """:func:`app.recon.compute_phase` of a capture set at its own bit depth and schedule.

    Raises:
        InvalidRequest: the frames do not fit the set's schedule (the reason names the key).
    """
    try:
        return compute_phase(capture.frames, capture.schedule, max_code=capture.max_code)
    except ValueError as exc:
        raise InvalidRequest(str(exc)) from None
