"""3-D measurements where the user clicks (issue 17): length,
point-to-line, depth, profile, area."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.api.deps import InstrumentDep, RecorderDep
from app.api.errors import COMMON, R400, R404, R409, R422
from app.api.schemas import MeasureIn, MeasureOut, MeasureToolIn, MeasureToolOut
from app.service.instrument import Instrument
from app.service.measure import calibration_terms, measure_result
from app.service.recorder import Recorder

router = APIRouter(prefix="/api", tags=["measure"])


def _measure(inst: Instrument, recorder: Recorder, body: MeasureIn) -> dict[str, Any]:
    spec = body.model_dump(exclude={"recording", "index"})
    normal, cal_sigma, cal_length = calibration_terms(inst.calibrations.calibration)
    if body.recording is not None and body.index is not None:
        res: Any = inst.calibrations.reconstruct(recorder.set_capture(body.recording, body.index))
        source: dict[str, Any] = {"recording": body.recording, "index": body.index}
    else:
        res = inst.latest_result()
        source = {"seq": res.seq, "created": res.created}
    out = measure_result(res, spec, normal, cal_sigma, cal_length, inst.calibrations.calibration)
    out["source"] = source
    return out


@router.post("/measure", response_model=MeasureOut,
             responses={**R400, **R404, **R409, **R422, **COMMON})
async def measure(body: MeasureIn, inst: InstrumentDep, recorder: RecorderDep) -> Any:
    """Measure in 3-D between clicked pixels, with the 1-σ uncertainty from the per-pixel σ.

    On the latest live result, or on set ``index`` of ``recording`` (reconstructed with the
    active calibration). A click on an invalid pixel snaps to the nearest valid one within
    ``snap_px`` (``snapped`` per point) or the answer is 422 naming the point and why."""
    return await run_in_threadpool(_measure, inst, recorder, body)


@router.get("/measure/tool", response_model=MeasureToolOut, responses=COMMON)
def tool_get(recorder: RecorderDep) -> dict[str, Any]:
    """The measurements kept on screen (copied into every recorded set's metadata)."""
    return {"measurements": recorder.measurements}


@router.put("/measure/tool", response_model=MeasureToolOut, responses={**R400, **R422, **COMMON})
def tool_put(body: MeasureToolIn, recorder: RecorderDep) -> dict[str, Any]:
    """Replace the measurements kept on screen; while recording, each recorded set's
    ``session.json`` entry and ``capture.json`` carry them, measured on that set's depth map."""
    recorder.measurements = [m.model_dump() for m in body.measurements]
    return {"measurements": recorder.measurements}
