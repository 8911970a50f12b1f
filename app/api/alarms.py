"""Alarms: faults shown on the dashboard until acknowledged (a recording that stopped)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path

from app.api.deps import AlarmsDep
from app.api.errors import COMMON, R404, R422
from app.api.schemas import AlarmOut

router = APIRouter(prefix="/api/alarms", tags=["control"])


# AlarmOut is built at run time from core.records.Alarm (schemas.model_of)
@router.get("", response_model=list[AlarmOut], responses=COMMON)  # type: ignore[valid-type]
def list_alarms(alarms: AlarmsDep, include_acknowledged: bool = False) -> list[dict[str, Any]]:
    """The alarms not yet acknowledged (with ``include_acknowledged``, every kept one)."""
    kept = alarms.all() if include_acknowledged else alarms.active()
    return [a.to_dict() for a in kept]


@router.post("/{alarm_id}/ack", response_model=AlarmOut, responses={**R404, **R422, **COMMON})
def acknowledge(alarm_id: Annotated[int, Path(ge=1, le=2**31)],
                alarms: AlarmsDep) -> dict[str, Any]:
    """Acknowledge an alarm: the dashboard stops showing it (acknowledging twice is harmless)."""
    return alarms.acknowledge(alarm_id).to_dict()
