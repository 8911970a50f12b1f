"""The instrument's fixed ranges (LEDs, exposure, bit depths, colormap range) for clients.

The dashboard reads these instead of repeating them in ``static/``.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api.deps import get_instrument
from app.api.errors import COMMON
from app.api.schemas import LimitsOut
from app.core.limits import EXPOSURE_RANGE_MS, LEDS, LIVE_BIT_DEPTHS
from app.outputs.encoding import DEFAULT_RANGE_MM
from app.service.instrument import Instrument

router = APIRouter(prefix="/api", tags=["control"])


@router.get("/limits", response_model=LimitsOut, responses=COMMON)
def limits(inst: Instrument = Depends(get_instrument)) -> LimitsOut:
    """LED names, the exposure range (ms), the camera's bit depths and the default depth colour range (mm)."""
    if inst.devices is not None:
        bit_depths = [int(b) for b in inst.devices.camera.capabilities.bit_depths]
    else:
        bit_depths = list(LIVE_BIT_DEPTHS)
    return LimitsOut(leds=list(LEDS), exposure_ms=list(EXPOSURE_RANGE_MS), bit_depths=bit_depths,
                     depth_range_mm=list(DEFAULT_RANGE_MM))
