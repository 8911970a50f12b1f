"""Live exposure bracketing through the lifespan on the twin's `anastomosis` scene: sets
alternate between the exposure and +2 stops, each pair fused per pixel; the status says the
depth rate halves; the valid share against single exposures is printed (the issue's figure)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.helpers.live_app import live_settings, wait_for


def _maps(client: TestClient, n: int, timeout_s: float, *, bracket: bool) -> list[dict[str, Any]]:
    """The next ``n`` new results' metadata, of the given kind (one set or a fused pair)."""
    out: list[dict[str, Any]] = []
    seen = client.get("/api/result/latest").json().get("seq", -1)
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        meta = client.get("/api/result/latest").json()
        if meta.get("seq", -1) != seen:
            seen = meta["seq"]
            if (meta.get("bracket_exposures_ms") is not None) == bracket:
                out.append(meta)
        time.sleep(0.05)
    assert len(out) == n, f"only {len(out)} of {n} maps (bracket={bracket}) in {timeout_s} s"
    return out


def _rate(client: TestClient, seconds: float) -> float:
    """Depth maps per second over ``seconds`` of wall time (results published)."""
    a = client.get("/api/status").json()["results_published"]
    time.sleep(seconds)
    return (client.get("/api/status").json()["results_published"] - a) / seconds


@pytest.mark.slow
def test_live_bracketing_fuses_pairs_and_says_the_rate_halves(
    tmp_path: Path, sim_calibration_file: Path
) -> None:
    settings = live_settings(
        tmp_path, sim_calibration_file, sim_scene="anastomosis", exposure_ms=20.0
    )
    app = create_app(settings)
    with TestClient(app) as client:
        wait_for(client, lambda s: s["results_published"] >= 2, 300, "first results")
        assert client.put("/api/mode", json={}).status_code == 422  # neither field: a clear 422
        plain = _maps(client, 3, 60, bracket=False)
        assert all(m["exposure_ms"] == 20.0 for m in plain)
        rate_plain = _rate(client, 8.0)

        r = client.put("/api/mode", json={"bracket": True})
        assert r.status_code == 200 and r.json() == {"mode": "set", "bracket": True}
        # rolling maps cannot fuse a pair: refused, naming the way out, nothing changed
        r = client.put("/api/mode", json={"rolling": True})
        assert r.status_code == 409 and '"bracket": false' in r.json()["detail"]
        fused = _maps(client, 3, 120, bracket=True)
        assert all(
            m["bracket_exposures_ms"] == [20.0, 80.0] and m["exposure_ms"] == 20.0 for m in fused
        )
        st = wait_for(client, lambda s: s["state"] == "running", 30, "running while bracketing")
        assert st["bracket"]["exposures_ms"] == [20.0, 80.0] and st["bracket"]["auto"] is False
        assert (
            "depth rate halves" in st["bracket"]["note"]
            and st["state_reason"] == st["bracket"]["note"]
        )
        assert st["mode"] == "set"
        rate_fused = _rate(client, 8.0)

        v_plain = sum(m["valid_fraction"] for m in plain) / len(plain)
        v_fused = sum(m["valid_fraction"] for m in fused) / len(fused)
        print(
            f"\nanastomosis live, 20 ms: valid {100 * v_plain:.1f} % at {rate_plain:.2f} maps/s; "
            f"bracketed 20 + 80 ms: valid {100 * v_fused:.1f} % at {rate_fused:.2f} maps/s"
        )
        assert v_fused > 2.0 * v_plain
        assert rate_fused < 0.75 * rate_plain

        r = client.put("/api/mode", json={"bracket": False})
        assert r.status_code == 200 and r.json() == {"mode": "set", "bracket": False}
        again = _maps(client, 2, 60, bracket=False)
        assert all(m["exposure_ms"] == 20.0 for m in again)
        st = client.get("/api/status").json()
        assert st["bracket"] is None
