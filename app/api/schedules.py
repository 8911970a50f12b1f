"""Fringe pattern schedules: the registered ones with their predicted
figures, and the one in use."""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter
from pydantic import BaseModel, Field

from app.api.deps import InstrumentDep
from app.api.errors import COMMON, R400, R409, R422
from app.api.schemas import Strict
from app.core.schedule import SCHEDULES

router = APIRouter(prefix="/api", tags=["control"])

ScheduleName = Literal[tuple(SCHEDULES)]  # type: ignore[valid-type]


class ScheduleOut(BaseModel):
    name: str
    frequencies: list[float]
    steps: int
    unwrap: str
    frames_per_depth: int
    predicted_sigma_mm: float | None = Field(
        description="median predicted 1-σ depth noise over the newest map's valid pixels, "
                    "mm (null: no map yet)")
    predicted_sigma_phi_rad: float = Field(description="median σ of the finest wrapped phase, rad")
    predicted_order_error_rate: float = Field(description="mean probability of a wrong "
                                                          "fringe order per pixel")
    prediction_source: Literal["live", "nominal"]
    calibration_applies: bool | None = Field(description="the active calibration maps this "
                                                         "schedule's phase (same finest pattern); "
                                                         "null: no calibration")
    calibration_note: str | None
    active: bool


class ScheduleIn(Strict):
    name: ScheduleName  # type: ignore[valid-type]


class ScheduleSet(BaseModel):
    name: str
    frames_per_depth: int
    applies: str = "from the next whole fringe set"


@router.get("/schedules", response_model=list[ScheduleOut], responses=COMMON)
def get_schedules(inst: InstrumentDep) -> list[dict[str, Any]]:
    """Every registered schedule with its predicted depth σ and order-error
    rate at the rig's noise."""
    return inst.schedules()


@router.put("/schedule", response_model=ScheduleSet, responses={**R400, **R409, **R422, **COMMON})
def put_schedule(body: ScheduleIn, inst: InstrumentDep) -> ScheduleSet:
    """Run another registered schedule (409 while recording or calibrating); the projector and the
    controller load its patterns between two sets."""
    name = inst.set_schedule(body.name)
    return ScheduleSet(name=name, frames_per_depth=SCHEDULES[name].n_frames)
