"""Measurements in a region of the latest depth map."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends
from starlette.concurrency import run_in_threadpool

from app.api.deps import get_instrument
from app.api.errors import COMMON, R400, R409, R422
from app.api.schemas import FeatureIn, FeatureOut, PlaneOut, RoiIn
from app.service import analysis
from app.service.instrument import Instrument

router = APIRouter(prefix="/api/analysis", tags=["analysis"])


@router.post("/plane", response_model=PlaneOut, responses={**R409, **R400, **R422, **COMMON})
async def plane(body: RoiIn, inst: Instrument = Depends(get_instrument)) -> Any:
    """Plane fit in the ROI: accuracy (mean distance), precision (std), flatness, point count."""
    return await run_in_threadpool(analysis.plane, inst.latest_result(), body.box)


@router.post("/feature", response_model=FeatureOut, responses={**R409, **R400, **R422, **COMMON})
async def feature(body: FeatureIn, inst: Instrument = Depends(get_instrument)) -> Any:
    """Height of a feature (e.g. a suture, bright or dark) above its surrounding baseline in the ROI."""
    cal = inst.calibration
    return await run_in_threadpool(analysis.feature, inst.latest_result(), body.box, body.polarity,
                                   None if cal is None else cal.plane_normal)
