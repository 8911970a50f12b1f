"""REST and stream routes (thin: every route calls one part of the instrument, see deps)."""

from __future__ import annotations

from fastapi import APIRouter

from app.api import (
    alarms,
    analysis,
    calibration,
    change,
    control,
    limits,
    measure,
    recordings,
    results,
    schedules,
    stream,
)


def api_router() -> APIRouter:
    router = APIRouter()
    for module in (control, alarms, limits, results, calibration, analysis, measure, recordings,
                   schedules, stream, change):
        router.include_router(module.router)
    return router


__all__ = ["api_router"]
