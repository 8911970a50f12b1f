"""The instrument's fixed ranges (LEDs, exposure, bit depths, colormap range) for clients.

The dashboard reads these instead of repeating them in ``static/``.
"""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import PipelineDep
from app.api.errors import COMMON
from app.api.schemas import LimitsOut
from app.core.limits import DEFAULT_DEPTH_RANGE_MM, EXPOSURE_RANGE_MS, LEDS, LIVE_BIT_DEPTHS

router = APIRouter(prefix="/api", tags=["control"])


@router.get("/limits", response_model=LimitsOut, responses=COMMON)
def limits(pipeline: PipelineDep) -> LimitsOut:
    """LED names, the exposure range (ms), the camera's bit depths and the default
    depth colour range (mm)."""
    bit_depths = list(pipeline.camera_bit_depths() or LIVE_BIT_DEPTHS)
    return LimitsOut(leds=list(LEDS), exposure_ms=list(EXPOSURE_RANGE_MS), bit_depths=bit_depths,
                     depth_range_mm=list(DEFAULT_DEPTH_RANGE_MM))
