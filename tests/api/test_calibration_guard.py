"""Calibrations are checked before they go live (the running app on the simulator).

A corrupted calibration file must be refused with 422 naming the reason, leave the active
calibration (and ``active.json``) as it was, and leave the live valid fraction where it was.
One that passes the physical checks but would leave far fewer valid pixels on the newest
frames is refused by the dry run unless ``force`` is given; forced, the status warns that the
live valid fraction collapsed.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.helpers.live_app import live_settings, wait_for

Corrupt = Callable[[dict[str, Any]], None]


def _fx_zero(d: dict[str, Any]) -> None:
    d["camera_matrix"][0][0] = 0.0


def _fx_flipped(d: dict[str, Any]) -> None:
    d["camera_matrix"][0][0] = -d["camera_matrix"][0][0]


def _region_nan(d: dict[str, Any]) -> None:
    d["model"]["supported_region"]["phase_rad"] = [float("nan"), float("nan")]


def _systematic_1e6(d: dict[str, Any]) -> None:
    d["held_out"][d["model"]["name"]]["systematic_mm"] = 1e6


def _projector_width(d: dict[str, Any]) -> None:
    d["model"]["projector_width_px"] = 912


CORRUPTIONS: dict[str, tuple[Corrupt, str]] = {  # name: (change, what the 422 must name)
    "fx = 0": (_fx_zero, "camera_matrix: focal lengths must be positive"),
    "fx sign flipped": (_fx_flipped, "camera_matrix: focal lengths must be positive"),
    "region [NaN, NaN]": (_region_nan, "model.supported_region.phase_rad"),
    "systematic term 1e6": (_systematic_1e6, "systematic_mm: must be finite and within"),
    "projector width": (_projector_width, "model.projector_width_px: 912 differs"),
}


@pytest.fixture(scope="module")
def app_client(tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path
               ) -> Iterator[tuple[TestClient, Path]]:
    data = tmp_path_factory.mktemp("guard")
    with TestClient(create_app(live_settings(data, sim_calibration_file))) as client:
        wait_for(client, lambda st: st["results_published"] >= 2, 120, "live results")
        yield client, data / "data" / "calibrations"


def _valid_fraction_after(client: TestClient, n_sets: int = 2) -> float:
    """The live valid fraction of a result reconstructed after this call."""
    done = client.get("/api/status").json()["results_published"]
    wait_for(client, lambda st: st["results_published"] >= done + n_sets, 60, "new results")
    r = client.get("/api/result/latest")
    assert r.status_code == 200, r.text
    return float(r.json()["valid_fraction"])


def _put(client: TestClient, body: dict[str, Any], query: str = "") -> Any:
    return client.put(f"/api/calibration/file{query}", content=json.dumps(body),
                      headers={"content-type": "application/json"})


def test_corrupted_calibrations_are_refused_and_change_nothing(
        app_client: tuple[TestClient, Path], sim_calibration_file: Path) -> None:
    client, folder = app_client
    good = json.loads(sim_calibration_file.read_text())
    active_before = client.get("/api/calibration").json()
    file_before = client.get("/api/calibration/file").content
    stored_before = (
        {p.name: p.read_bytes() for p in folder.glob("*.json")} if folder.is_dir() else {}
    )
    fraction_before = _valid_fraction_after(client)
    assert fraction_before > 0.3  # the 45° target is mostly measured

    for name, (corrupt, reason) in CORRUPTIONS.items():
        bad = copy.deepcopy(good)
        corrupt(bad)
        r = _put(client, bad)
        assert r.status_code == 422, (name, r.text)
        assert reason in r.json()["detail"], (name, r.json())
        assert r.json()["detail"].count("\n") == 0
    # a well-formed calibration sent as text/plain
    r = client.put(
        "/api/calibration/file", content=json.dumps(good), headers={"content-type": "text/plain"}
    )
    assert r.status_code == 422 and "Content-Type must be application/json" in r.json()["detail"], (
        r.text
    )
    # force skips the dry run, never the physical checks
    r = _put(client, _corrupted(good, _fx_zero), "?force=true")
    assert r.status_code == 422 and "focal lengths" in r.json()["detail"]

    assert client.get("/api/calibration").json() == active_before
    assert client.get("/api/calibration/file").content == file_before
    stored_after = (
        {p.name: p.read_bytes() for p in folder.glob("*.json")} if folder.is_dir() else {}
    )
    assert stored_after == stored_before and "active.json" not in stored_after
    fraction_after = _valid_fraction_after(client)
    assert abs(fraction_after - fraction_before) < 0.02, (fraction_before, fraction_after)
    assert not any("collapsed" in w for w in client.get("/api/status").json()["warnings"])


def test_dry_run_refuses_a_collapse_unless_forced_and_the_status_warns(
        app_client: tuple[TestClient, Path], sim_calibration_file: Path) -> None:
    client, folder = app_client
    good = json.loads(sim_calibration_file.read_text())
    fraction_before = _valid_fraction_after(client)
    # physically plausible, but its region admits a sliver of the phase range the scene spans
    narrow = copy.deepcopy(good)
    lo, _ = narrow["model"]["supported_region"]["phase_rad"]
    narrow["model"]["supported_region"]["phase_rad"] = [lo, lo + 1.0]
    r = _put(client, narrow)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "dry run on the newest frames" in detail and "force=true" in detail, detail
    assert client.get("/api/calibration").json()["name"] == "sim"
    assert not (folder / "active.json").exists()
    assert abs(_valid_fraction_after(client) - fraction_before) < 0.02

    r = _put(client, narrow, "?force=true")
    assert r.status_code == 200 and r.json()["name"] == "uploaded", r.text
    assert json.loads((folder / "active.json").read_text())["model"]["supported_region"][
        "phase_rad"
    ] == [lo, lo + 1.0]
    st = wait_for(
        client, lambda s: any("collapsed" in w for w in s["warnings"]), 60, "collapse warning"
    )
    warning = next(w for w in st["warnings"] if "collapsed" in w)
    assert "after activating calibration 'uploaded'" in warning, warning
    assert _valid_fraction_after(client) < 0.5 * fraction_before

    # the good one goes back (the dry run compares with the collapsed one: no refusal)
    r = _put(client, good)
    assert r.status_code == 200, r.text
    assert abs(_valid_fraction_after(client, 3) - fraction_before) < 0.02
    assert not any("collapsed" in w for w in client.get("/api/status").json()["warnings"])


def _corrupted(good: dict[str, Any], corrupt: Corrupt) -> dict[str, Any]:
    bad = copy.deepcopy(good)
    corrupt(bad)
    return bad
