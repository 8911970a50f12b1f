"""Per-pixel reason codes: why a pixel has no depth.

When several apply, the reported code follows the chain of causes, first match wins:

    SATURATED > MOTION > LOW_MODULATION > UNWRAP_INCONSISTENT > MODEL_SINGULAR > OUTSIDE_VOLUME
    > OUTSIDE_FIELD > UNCERTAIN

MOTION (the scene moved while the set was taken: the background of the frequency groups
disagrees beyond the sensor noise, see :mod:`app.recon.motion`) is set by the live
service after the engine; a pixel that moved has a meaningless phase, so it outranks every
phase-derived code, but a clipped frame is the earlier cause.
A clipped pixel has a meaningless phase and so usually also low modulation or a bad
unwrap; a pixel without fringe contrast usually also unwraps badly; a singular model
yields a height far outside the volume; a height outside the calibrated volume is also
outside the region the calibration's data support (OUTSIDE_FIELD: inside the volume but
where the boards did not reach, or outside the projector's calibrated field); UNCERTAIN
(σ above the optional ``max_sigma_mm``) is the last resort. Reporting the earliest cause
tells the user what to change (exposure, focus/LED power, calibration).
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
import numpy.typing as npt


class Reason(IntEnum):
    """``uint8`` code stored per pixel in ``ReconResult.reason``."""

    OK = 0
    LOW_MODULATION = 1
    SATURATED = 2
    UNWRAP_INCONSISTENT = 3
    OUTSIDE_VOLUME = 4
    MODEL_SINGULAR = 5
    OUTSIDE_FIELD = 6
    UNCERTAIN = 7
    MOTION = 8


#: Codes ordered from highest to lowest precedence (OK last).
PRECEDENCE: tuple[Reason, ...] = (
    Reason.SATURATED,
    Reason.MOTION,
    Reason.LOW_MODULATION,
    Reason.UNWRAP_INCONSISTENT,
    Reason.MODEL_SINGULAR,
    Reason.OUTSIDE_VOLUME,
    Reason.OUTSIDE_FIELD,
    Reason.UNCERTAIN,
    Reason.OK,
)


def assign_reasons(
    shape: tuple[int, ...],
    *,
    saturated: npt.ArrayLike | None = None,
    low_modulation: npt.ArrayLike | None = None,
    inconsistent: npt.ArrayLike | None = None,
    singular: npt.ArrayLike | None = None,
    outside: npt.ArrayLike | None = None,
    outside_field: npt.ArrayLike | None = None,
    uncertain: npt.ArrayLike | None = None,
    motion: npt.ArrayLike | None = None,
) -> npt.NDArray[np.uint8]:
    """Combine boolean masks into one uint8 reason map, honouring :data:`PRECEDENCE`."""
    out = np.zeros(shape, dtype=np.uint8)
    # lowest precedence first, so higher ones overwrite
    for mask, code in (
        (uncertain, Reason.UNCERTAIN),
        (outside_field, Reason.OUTSIDE_FIELD),
        (outside, Reason.OUTSIDE_VOLUME),
        (singular, Reason.MODEL_SINGULAR),
        (inconsistent, Reason.UNWRAP_INCONSISTENT),
        (low_modulation, Reason.LOW_MODULATION),
        (motion, Reason.MOTION),
        (saturated, Reason.SATURATED),
    ):
        if mask is not None:
            out[np.broadcast_to(np.asarray(mask, dtype=bool), shape)] = code
    return out
