"""The alarm routes on the real app (not started: the alarm board needs no devices)."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app


def test_acknowledge_route_typed_and_documented(tmp_path: Path) -> None:
    app = create_app(Settings(data_dir=tmp_path, viewer=False, autostart=False))
    client = TestClient(app)  # no lifespan: the instrument is built, not started
    alarm = app.state.instrument.alarms.raise_alarm("recorder", "recording 'x' stopped: disk full")

    st = client.get("/api/status")
    assert st.status_code == 200 and st.headers["content-type"] == "application/json"
    assert [a["message"] for a in st.json()["alarms"]] == [alarm.message]
    listed = client.get("/api/alarms").json()
    assert [a["id"] for a in listed] == [alarm.id] and listed[0]["acknowledged_at"] is None
    r = client.post(f"/api/alarms/{alarm.id}/ack")
    assert r.status_code == 200, r.text
    assert r.json()["id"] == alarm.id and r.json()["acknowledged_at"]
    assert client.get("/api/alarms").json() == []
    assert client.get("/api/status").json()["alarms"] == []
    assert len(client.get("/api/alarms", params={"include_acknowledged": True}).json()) == 1

    r = client.post("/api/alarms/99/ack")
    assert r.status_code == 404 and "no alarm 99" in r.json()["detail"]
    for bad in ("0", "abc", "1e400"):
        assert client.post(f"/api/alarms/{bad}/ack").status_code == 422, bad

    paths = client.get("/openapi.json").json()["paths"]
    ack = paths["/api/alarms/{alarm_id}/ack"]["post"]
    assert {"200", "404", "422"} <= set(ack["responses"])
    ok_schema = ack["responses"]["200"]["content"]["application/json"]["schema"]
    assert ok_schema["$ref"].endswith("AlarmOut")
    assert "/api/alarms" in paths
    status_props = client.app.openapi()["components"]["schemas"]["StatusOut"]["properties"]
    assert "alarms" in status_props
