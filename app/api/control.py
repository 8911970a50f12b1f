"""Status and control: exposure, LED, mode, acquisition start/stop."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from fastapi import APIRouter, Body
from fastapi.responses import Response

from app.api.deps import InstrumentDep, InstrumentNowDep, PipelineDep
from app.api.errors import COMMON, R400, R409, R422
from app.api.schemas import (
    AcquisitionOut,
    AutoExposureIn,
    AutoExposureOut,
    ExposureIn,
    ExposureOut,
    LedIn,
    LedOut,
    ModeIn,
    ModeOut,
    StatusOut,
)
from app.core.errors import Conflict

router = APIRouter(prefix="/api", tags=["control"])


@router.get("/status", response_model=StatusOut, responses=COMMON)
async def status(inst: InstrumentNowDep) -> Response:
    """State, rates, latency, settings, calibration, devices and counters."""
    # on the event loop, no worker-thread hop: the record is a few reads of counters (well
    # under a millisecond), and pollers must not queue behind busy threads for it
    body = StatusOut.model_validate(inst.status().to_dict()).model_dump_json()
    return Response(body, media_type="application/json")


@router.put("/exposure", response_model=ExposureOut, responses={**R400, **R422, **COMMON})
def put_exposure(body: ExposureIn, inst: InstrumentDep) -> ExposureOut:
    """Camera exposure (1–100 ms), applied from the next whole fringe set."""
    return ExposureOut(exposure_ms=inst.set_exposure(body.exposure_ms))


@router.post("/exposure/auto", response_model=AutoExposureOut,
             responses={**R409, **R400, **R422, **COMMON})
def auto_exposure(
    pipeline: PipelineDep,
    body: AutoExposureIn = Body(default_factory=AutoExposureIn),
) -> Any:
    """Longest exposure whose sets keep saturation under the limit (grabs a few real sets); then
    exposure bracketing on if more than 10 % of the lit, unsaturated pixels stay invalid for low
    signal at it (the scene spans more than one exposure), off otherwise."""
    res = pipeline.auto_exposure(saturation_limit=body.saturation_limit,
                                 max_exposure_ms=body.max_exposure_ms)
    return {**asdict(res), "bracket": pipeline.bracketing,
            "low_signal_share": pipeline.bracket_dim_share}


@router.put("/led", response_model=LedOut, responses={**R400, **R422, **COMMON})
def put_led(body: LedIn, inst: InstrumentDep) -> LedOut:
    """Projector LED, applied from the next whole fringe set."""
    return LedOut(led=inst.set_led(body.led))


@router.put("/mode", response_model=ModeOut, responses={**R400, **R409, **R422, **COMMON})
def put_mode(body: ModeIn, inst: InstrumentDep) -> ModeOut:
    """Rolling mode (a depth map after every frame from the last 16, motion-masked) and/or
    exposure bracketing (whole sets alternate between the exposure and +2 stops, each pair fused
    per pixel: half the depth rate). Both at once: 409."""
    if body.rolling and body.bracket:
        raise Conflict("mode: rolling maps cannot fuse an exposure bracket; ask for one of them")
    if body.bracket is False:
        inst.set_bracket(False)
    if body.rolling is not None:
        inst.set_rolling(body.rolling)
    if body.bracket:
        inst.set_bracket(True)
    acq = inst.acquisition
    return ModeOut(mode="rolling" if acq is not None and acq.rolling else "set",
                   bracket=inst.pipeline.bracketing)


@router.post("/acquisition/start", response_model=AcquisitionOut, responses=COMMON)
def start(inst: InstrumentDep) -> AcquisitionOut:
    inst.pipeline.set_acquiring(True)
    return AcquisitionOut(acquiring=True, state=inst.state())


@router.post("/acquisition/stop", response_model=AcquisitionOut, responses=COMMON)
def stop(inst: InstrumentDep) -> AcquisitionOut:
    inst.pipeline.set_acquiring(False)
    return AcquisitionOut(acquiring=False, state=inst.state())
