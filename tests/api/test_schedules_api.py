"""Schedules through the lifespan: the table with predictions, switching, refusals, and the
carry-over rule."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from app.calib import load_calibration
from app.config import Settings
from app.core.schedule import SCHEDULES, PatternSchedule
from app.service.instrument import Instrument
from tests.helpers.live_app import wait_for, wait_result


def test_schedules_table_predicts_from_the_live_rig(live: TestClient) -> None:
    rows = {r["name"]: r for r in live.get("/api/schedules").json()}
    assert list(rows) == list(SCHEDULES)
    assert [n for n, r in rows.items() if r["active"]] == ["paper-16"]
    for name, r in rows.items():
        s = SCHEDULES[name]
        assert r["frequencies"] == list(s.frequencies) and r["steps"] == s.steps
        assert r["frames_per_depth"] == s.n_frames
        assert r["prediction_source"] == "live" and r["calibration_applies"] is True
        assert 0.0 <= r["predicted_order_error_rate"] < 1e-3
        assert 0.0 < r["predicted_sigma_mm"] < 0.5
    # same pixels, same finest pattern: σ scales as √(2/N) exactly (medians of scaled values)
    ratio = rows["geometric-9"]["predicted_sigma_mm"] / rows["paper-16"]["predicted_sigma_mm"]
    assert ratio == pytest.approx(math.sqrt(4 / 3), rel=1e-3)
    assert rows["geometric-12"]["predicted_sigma_mm"] == pytest.approx(
        rows["paper-16"]["predicted_sigma_mm"], rel=1e-3
    )
    # fewer, farther-apart frequencies unwrap less reliably
    assert (
        rows["paper-16"]["predicted_order_error_rate"]
        <= rows["geometric-12"]["predicted_order_error_rate"]
    )
    assert (
        rows["geometric-9"]["predicted_order_error_rate"]
        <= rows["heterodyne-9"]["predicted_order_error_rate"]
    )


@pytest.mark.parametrize("body", [{"name": "nope"}, {"name": 5}, {}, {"name": "paper-16", "x": 1}])
def test_bad_schedule_is_422(live: TestClient, body: object) -> None:
    r = live.put("/api/schedule", json=body)
    assert r.status_code == 422
    assert live.get("/api/status").json()["schedule"]["name"] == "paper-16"


def test_switch_reloads_the_devices_and_keeps_the_calibration(live: TestClient) -> None:
    try:
        r = live.put("/api/schedule", json={"name": "geometric-9"})
        assert r.status_code == 200, r.text
        assert r.json()["frames_per_depth"] == 9
        st = live.get("/api/status").json()
        assert st["schedule"]["name"] == "geometric-9" and st["schedule"]["frequencies"] == [
            1,
            6,
            36,
        ]
        assert st["schedule"]["steps"] == 3 and st["schedule"]["frames_per_depth"] == 9
        assert st["schedule"]["calibration_applies"] is True
        meta = wait_result(live, lambda m: len(m["frame_indices"]) == 9, 60, "a 9-frame depth map")
        assert meta["valid_fraction"] > 0.3
        projector = next(d for d in st["devices"] if d["kind"] == "projector")
        assert projector["state"] in ("running", "open")
        rows = {x["name"]: x for x in live.get("/api/schedules").json()}
        assert rows["geometric-9"]["active"] and not rows["paper-16"]["active"]
        # idempotent
        assert live.put("/api/schedule", json={"name": "geometric-9"}).status_code == 200
    finally:
        assert live.put("/api/schedule", json={"name": "paper-16"}).status_code == 200
    wait_result(live, lambda m: len(m["frame_indices"]) == 16, 60, "a 16-frame depth map again")
    wait_for(live, lambda s: s["schedule"]["name"] == "paper-16" and not s["warnings"], 10)


def test_switch_is_refused_while_recording(live: TestClient) -> None:
    assert live.post("/api/recording/start", json={"name": "sched-rec"}).status_code == 200
    try:
        r = live.put("/api/schedule", json={"name": "geometric-9"})
        assert r.status_code == 409 and "recording" in r.json()["detail"]
    finally:
        live.post("/api/recording/stop")
    assert live.get("/api/status").json()["schedule"]["name"] == "paper-16"


def test_switch_is_refused_while_calibrating(live: TestClient) -> None:
    """Last in the module: the wizard's session stays open."""
    board = {"type": "checkerboard", "inner_corners": [9, 6], "square_mm": 2.0}
    assert live.post("/api/calibration/session", json=board).status_code == 200
    r = live.put("/api/schedule", json={"name": "geometric-9"})
    assert r.status_code == 409 and "calibration" in r.json()["detail"]


def test_setting_names_the_schedule(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FRINGESCOPE_SCHEDULE", "geometric-9")
    assert Settings().schedule == "geometric-9"
    monkeypatch.setenv("FRINGESCOPE_SCHEDULE", "nope")
    with pytest.raises(ValidationError, match="unknown name 'nope'"):
        Settings()


def test_calibration_that_does_not_apply_is_never_used(
    tmp_path: Path, sim_calibration_file: Path
) -> None:
    """The carry-over rule in the service: another finest pattern → no engine, and the status says
    why."""
    inst = Instrument(
        Settings(data_dir=tmp_path, viewer=False, autostart=False, schedule="geometric-9")
    )
    try:
        assert (
            inst.schedule == SCHEDULES["geometric-9"]
            and inst.status().to_dict()["schedule"]["name"] == "geometric-9"
        )
        cal = load_calibration(sim_calibration_file)  # made with paper-16: carries over
        inst.calibrations.activate(cal, name="sim", persist=False)
        assert (
            inst.pipeline.has_engine
            and inst.status().to_dict()["schedule"]["calibration_applies"] is True
        )
        assert inst.pipeline._live_engine().calibration.pattern == SCHEDULES["geometric-9"]  # type: ignore[union-attr]
        # finest 12: its phase is another projector coordinate
        other = PatternSchedule((1, 4, 12), 4)
        inst.pipeline.set_schedule(other, inst.calibrations.engine_for)
        st = inst.status().to_dict()
        assert not inst.pipeline.has_engine and st["schedule"]["calibration_applies"] is False
        assert st["schedule"]["name"] is None
        assert any("does not apply" in w and "finest" in w for w in st["warnings"])
        why = inst.pipeline.why_no_result()
        assert why is not None and "does not apply" in str(why)
        rows = {r["name"]: r for r in inst.schedules()}
        assert all(r["calibration_applies"] for r in rows.values()) and not any(
            r["active"] for r in rows.values()
        )
        assert (
            rows["paper-16"]["prediction_source"] == "nominal"
            and rows["paper-16"]["predicted_sigma_mm"] is None
        )
        inst.pipeline.set_schedule(SCHEDULES["paper-16"], inst.calibrations.engine_for)
        assert inst.pipeline.has_engine and not inst.status().to_dict()["warnings"]
        with pytest.raises(ValueError, match="orientation"):  # activation checks the same rule
            horizontal = load_calibration(sim_calibration_file)
            horizontal.pattern = PatternSchedule(orientation="horizontal")
            inst.calibrations.activate(horizontal, name="h", persist=False)
    finally:
        inst.close()
