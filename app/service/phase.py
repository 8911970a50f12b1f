"""Calibration-free decoding of a capture set (``fringescope phase`` and ``POST /api/phase``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from app.capture.captureset import CaptureSet
    from app.recon.reconstructor import PhaseResult


def decode_capture(capture: CaptureSet) -> PhaseResult:
    """:func:`app.recon.compute_phase` of a capture set at its own bit depth and schedule."""
    from app.recon import compute_phase

    return compute_phase(capture.frames, capture.schedule, max_code=capture.max_code)
