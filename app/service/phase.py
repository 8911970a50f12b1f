"""Calibration-free decoding of a capture set (``fringescope phase`` and ``POST /api/phase``)."""

from __future__ import annotations

from app.capture.captureset import CaptureSet
from app.core.errors import InvalidRequest
from app.recon import compute_phase
from app.recon.gamma import PhaseErrorLUT
from app.recon.reconstructor import PhaseResult


def decode_capture(capture: CaptureSet, phase_error: PhaseErrorLUT | None = None, *,
                   min_modulation: float | None = None) -> PhaseResult:
    """:func:`app.recon.compute_phase` of a capture set at its own bit depth and schedule,
    with a projector-gamma table (``fringescope gamma``) subtracted when given, and an
    explicit modulation threshold (codes) instead of the noise-aware rule when given.

    Raises:
        InvalidRequest: the frames do not fit the set's schedule (the reason names the key).
    """
    try:
        if phase_error is not None:
            phase_error.check_schedule(capture.schedule.steps, capture.schedule.frequencies)
        return compute_phase(capture.frames, capture.schedule, max_code=capture.max_code,
                             phase_error=phase_error, min_modulation=min_modulation)
    except ValueError as exc:
        raise InvalidRequest(str(exc)) from None
