"""Typed records → the JSON objects the REST API documents."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from pydantic import BaseModel

from app.api.schemas import CalibrationSummary as CalibrationSummaryOut
from app.api.schemas import DeviceOut, StatusOut, model_of
from app.core.records import CalibrationSummary, DeviceStatus, Status


def _status(calibration: CalibrationSummary | None) -> Status:
    return Status(
        state="running", camera_fps=33.3, depth_fps=2.08, latency_ms=12.5, recon_ms=None,
        exposure_ms=30.0, led="green", mode="set", acquiring=True, calibration=calibration,
        devices=(DeviceStatus("sim-camera", "camera", "running"),
                 DeviceStatus("lcr", "projector", "fault", "gone")),
        last_error="gone", sets_completed=4, results_published=3, dropped_sets=1,
        incomplete_sets=0, mixed_sets=0, frames_received=70, frames_dropped=2, faults=1,
        recording=None, warnings=("w1",),
    )


def test_status_dict_is_json_and_matches_the_api_schema():
    cal = CalibrationSummary("sim", "2026-11-24T01:00:00+00:00", (0.0, 22.5), (1384, 1032), "0.1",
                             8)
    for summary in (cal, None):
        d = _status(summary).to_dict()
        assert json.loads(json.dumps(d)) == d
        out = StatusOut.model_validate(d)
        assert out.model_dump(mode="json") == d
    assert d["devices"][1] == {"name": "lcr", "kind": "projector", "state": "fault",
                               "error": "gone"}


def test_calibration_summary_lists():
    d = CalibrationSummary("x", "t", (1.0, 2.0), (640, 480), "v", 3).to_dict()
    assert d["height_range_mm"] == [1.0, 2.0] and d["image_size"] == [640, 480]
    assert CalibrationSummaryOut.model_validate(d).model_dump() == d



def _defaults(model: type[Any]) -> dict[str, object]:
    """Field name → default (absent: required) of a dataclass or a pydantic model."""
    if issubclass(model, BaseModel):
        return {name: f.get_default(call_default_factory=True)
                for name, f in model.model_fields.items() if not f.is_required()}
    out: dict[str, object] = {}
    for f in dataclasses.fields(model):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def test_api_models_have_the_records_fields_and_agreeing_defaults() -> None:
    pairs: tuple[tuple[type[Any], type[BaseModel]], ...] = (
        (Status, StatusOut), (CalibrationSummary, CalibrationSummaryOut), (DeviceStatus, DeviceOut))
    for record, model in pairs:
        assert [f.name for f in dataclasses.fields(record)] == list(model.model_fields), record
        ours, theirs = _defaults(record), _defaults(model)
        disagree = {k: (ours[k], theirs[k]) for k in ours.keys() & theirs.keys()
                    if json.dumps(ours[k]) != json.dumps(theirs[k])}
        assert not disagree, f"{record.__name__}: defaults differ {disagree}"


@dataclasses.dataclass(frozen=True)
class Inner:
    size: tuple[int, int]


@dataclasses.dataclass(frozen=True)
class Outer:
    items: tuple[Inner, ...]
    best: Inner | None
    span_mm: float = dataclasses.field(default=1.5, metadata={"description": "how far, mm"})
    tags: tuple[str, ...] = ()


def test_api_models_are_derived_from_the_records() -> None:
    """A field written in a record is in its API model: type, default, description, order."""
    inner = model_of(Inner, "InnerOut")
    outer = model_of(Outer, "OuterOut", {Inner: inner})
    assert list(outer.model_fields) == ["items", "best", "span_mm", "tags"]
    schema = outer.model_json_schema()
    assert schema["required"] == ["items", "best"]
    assert schema["properties"]["span_mm"]["description"] == "how far, mm"
    assert schema["properties"]["tags"] == {"default": [], "items": {"type": "string"},
                                            "title": "Tags", "type": "array"}
    assert schema["$defs"]["InnerOut"]["properties"]["size"]["type"] == "array"
    got = outer.model_validate({"items": [{"size": [3, 4]}], "best": None})
    assert got.model_dump() == {"items": [{"size": [3, 4]}], "best": None, "span_mm": 1.5,
                                "tags": []}
    assert StatusOut.model_fields["calibration"].annotation == CalibrationSummaryOut | None
    assert StatusOut.model_fields["state"].description == \
        dataclasses.fields(Status)[0].metadata["description"]
