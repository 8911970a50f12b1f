"""Measurements in a region of the latest depth map."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.api.deps import CalibrationsDep, InstrumentDep
from app.api.errors import COMMON, R400, R409, R422
from app.api.schemas import FeatureIn, FeatureOut, PlaneOut, RoiIn
from app.service import analysis

router = APIRouter(prefix="/api/analysis", tags=["analysis"])


@router.post("/plane", response_model=PlaneOut, responses={**R409, **R400, **R422, **COMMON})
async def plane(body: RoiIn, inst: InstrumentDep) -> Any:
    """Plane fit in the ROI: accuracy (mean distance), precision (std), flatness, point count."""
    return await run_in_threadpool(analysis.plane, inst.latest_result(), body.box)


@router.post("/feature", response_model=FeatureOut, responses={**R409, **R400, **R422, **COMMON})
async def feature(body: FeatureIn, inst: InstrumentDep,
                  calibrations: CalibrationsDep) -> Any:
    """Height of a feature (e.g. a suture, bright or dark) above its
    surrounding baseline in the ROI."""
    cal = calibrations.calibration
    return await run_in_threadpool(analysis.feature, inst.latest_result(), body.box, body.polarity,
                                   None if cal is None else cal.plane_normal)
