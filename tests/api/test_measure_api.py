"""POST /api/measure and the measure tool on the live simulator (lifespan running), and on a
recording."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.analysis.measure import measure
from app.capture.captureset import read_capture_set
from app.service.measure import calibration_terms
from tests.helpers.live_app import wait_for


def valid_pixels(
    valid: np.ndarray, n: int, rng: np.random.Generator, margin: int = 40
) -> list[list[int]]:
    vv, uu = np.nonzero(valid[margin:-margin, margin:-margin])
    k = rng.choice(len(uu), n, replace=False)
    return [[int(uu[i] + margin), int(vv[i] + margin)] for i in k]


@pytest.mark.serial
def test_measure_on_the_latest_result_matches_the_functions(live: TestClient) -> None:
    inst = live.app.state.instrument  # type: ignore[attr-defined]
    assert live.post("/api/acquisition/stop").status_code == 200  # hold the latest result still
    try:
        time.sleep(0.5)
        res = inst.latest_result()
        rng = np.random.default_rng(3)
        for kind, n in (
            ("length", 2),
            ("point_to_line", 3),
            ("depth", 4),
            ("profile", 2),
            ("area", 4),
        ):
            pix = valid_pixels(res.valid, n, rng)
            if kind == "area":  # a convex quadrilateral around the image centre
                h, w = res.valid.shape
                pix = [
                    [w // 3, h // 3],
                    [2 * w // 3, h // 3],
                    [2 * w // 3, 2 * h // 3],
                    [w // 3, 2 * h // 3],
                ]
            r = live.post("/api/measure", json={"kind": kind, "points": pix})
            if r.status_code == 422:  # e.g. the area's polygon covering a hole in the surface
                assert kind == "area" and "point" in r.json()["detail"], r.text
                continue
            assert r.status_code == 200, r.text
            body = r.json()
            assert body["source"]["seq"] == res.seq
            normal, cal_sigma, cal_length = calibration_terms(inst.calibration)
            held = inst.calibration.held_out[inst.calibration.model.name]
            assert (cal_sigma, cal_length) == (held["systematic_mm"], held["correlation_mm"])
            # the noise part independent between pixels, the calibration's by its covariance
            ref = measure(kind, res.points, res.valid, res.sigma_noise, pix, plane_normal=normal,
                          calibration_sigma_mm=cal_sigma, calibration_length_mm=cal_length,
                          calibration=inst.calibration)
            assert body["value_mm"] == pytest.approx(ref.value_mm, rel=1e-9)
            assert (
                body["sigma_mm"] == pytest.approx(ref.sigma_mm, rel=1e-9) and body["sigma_mm"] > 0
            )
            assert 0 < body["extra"]["sigma_noise_mm"] <= body["sigma_mm"]
            assert [p["pixel"] for p in body["points"]] == pix
            assert all(np.isfinite(p["point_mm"]).all() for p in body["points"])
            assert (body["profile"] is not None) == (kind == "profile")
            # the 100 ms target is timed by benchmarks/bench_measure.py
            assert body["elapsed_ms"] < 500
    finally:
        assert live.post("/api/acquisition/start").status_code == 200


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        (
            {"kind": "length", "points": [[-5, 10], [20, 20]]},
            "length: point 1 (-5, 10): outside the",
        ),
        ({"kind": "length", "points": [[10, 10]]}, "length: needs exactly 2 points, got 1"),
        (
            {"kind": "area", "points": [[100, 100], [200, 100]]},
            "area: needs at least 3 points, got 2",
        ),
        (
            {
                "kind": "length",
                "points": [[10, 10], [20, 20]],
                "reference": [[1, 1], [5, 1], [1, 5]],
            },
            "reference: only a profile",
        ),
        ({"kind": "volume", "points": [[10, 10], [20, 20]]}, None),
        (
            {"kind": "length", "points": [[10, 10], [20, 20]], "recording": "nope"},
            "recording and index",
        ),
    ],
)
def test_bad_clicks_are_422_with_one_line(live: TestClient, body: dict, needle: str | None) -> None:
    r = live.post("/api/measure", json=body)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    # pydantic's list, from the schema
    if needle is not None and isinstance(body.get("recording"), str):
        assert needle in str(detail), detail
    elif needle is not None:
        assert isinstance(detail, str) and "\n" not in detail and needle in detail, detail


def test_degenerate_line_and_plane_are_422(live: TestClient) -> None:
    res = live.app.state.instrument.latest_result()  # type: ignore[attr-defined]
    a, b, c = valid_pixels(res.valid, 3, np.random.default_rng(11))
    r = live.post("/api/measure", json={"kind": "depth", "points": [a, b, c, c]})
    assert (
        r.status_code == 422
        and "points 2 " in r.json()["detail"]
        and "collinear or coincident" in r.json()["detail"]
    ), r.text
    r = live.post("/api/measure", json={"kind": "point_to_line", "points": [a, b, b]})
    assert (
        r.status_code == 422
        and "points 2 and 3" in r.json()["detail"]
        and "coincide" in r.json()["detail"]
    )


def test_invalid_click_snaps_or_names_the_point(live: TestClient) -> None:
    inst = live.app.state.instrument  # type: ignore[attr-defined]
    res = inst.latest_result()
    bad = np.argwhere(~res.valid)
    h, w = res.valid.shape
    # an invalid pixel with no valid pixel within 2 px, and one next to a valid pixel
    from scipy.ndimage import binary_dilation

    near = binary_dilation(res.valid, iterations=2)
    far = np.argwhere(~near)
    edge = np.argwhere(~res.valid & binary_dilation(res.valid))
    good = valid_pixels(res.valid, 1, np.random.default_rng(0))[0]
    if len(far):
        v, u = (int(x) for x in far[0])
        r = live.post(
            "/api/measure", json={"kind": "length", "points": [good, [u, v]], "snap_px": 2}
        )
        # the live map may have changed meanwhile; it names the point either way
        if r.status_code == 422:
            assert "point 2" in r.json()["detail"]
    if len(edge):
        v, u = (int(x) for x in edge[len(edge) // 2])
        r = live.post("/api/measure", json={"kind": "length", "points": [good, [u, v]]})
        if r.status_code == 200:
            p = r.json()["points"][1]
            assert p["snapped"] == (p["pixel"] != [u, v]) and p["snap_px"] <= 3
    assert len(bad) < h * w


def test_recorded_sets_carry_the_tool_measurements(live: TestClient) -> None:
    # the module's running app (a second simulated instrument beside it starves both of CPU
    # on a 2-core machine: frames drop and no whole set completes)
    client = live
    settings = client.app.state.settings  # type: ignore[attr-defined]
    try:
        wait_for(client, lambda s: s["results_published"] >= 1, 300, "first result")
        res = client.app.state.instrument.latest_result()  # type: ignore[attr-defined]
        pix = valid_pixels(res.valid, 2, np.random.default_rng(5))
        tool = {
            "measurements": [
                {"kind": "length", "points": pix},
                {"kind": "length", "points": [[-1, -9], pix[0]]},
            ]
        }
        r = client.put("/api/measure/tool", json=tool)
        assert r.status_code == 200 and len(r.json()["measurements"]) == 2
        assert client.get("/api/measure/tool").json()["measurements"][0]["points"] == pix
        assert client.post("/api/recording/start", json={"name": "m-1"}).status_code == 200
        wait_for(
            client,
            lambda s: client.get("/api/recording").json()["sets_with_depth"] >= 2,
            180,
            "two sets",
        )
        session = client.post("/api/recording/stop").json()["stopped"]
        sets = [s for s in session["sets"] if s["depth"]]
        # the refused measurement (a click outside the image) is never stored as one
        assert sets and all(len(s["measurements"]) == 1 for s in sets)
        assert not any("error" in m for s in session["sets"] for m in s.get("measurements", []))
        first = sets[0]
        (good,) = first["measurements"]
        assert good["kind"] == "length" and good["value_mm"] > 0 and good["sigma_mm"] > 0
        assert good["coverage"] == 1.0
        cap = read_capture_set(Path(settings.data_dir) / "recordings" / "m-1" / first["folder"])
        assert cap.extra["measurements"] == first["measurements"]
        # the same measurement on the recorded set, reconstructed with the active calibration
        index = int(first["folder"].split("_")[1])
        r = client.post(
            "/api/measure",
            json={"kind": "length", "points": pix, "recording": "m-1", "index": index},
        )
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["source"] == {"recording": "m-1", "index": index}
        # the recorder measured the live result, the route a fresh reconstruction of the same frames
        assert body["value_mm"] == pytest.approx(good["value_mm"], abs=4 * body["sigma_mm"] + 1e-3)
        r = client.post(
            "/api/measure",
            json={"kind": "length", "points": pix, "recording": "m-1", "index": 9999},
        )
        assert r.status_code == 404 and "no set 9999" in r.json()["detail"]
        r = client.post(
            "/api/measure", json={"kind": "length", "points": pix, "recording": "none", "index": 0}
        )
        assert r.status_code == 404
    finally:  # restore what this test changed on the shared app
        if client.get("/api/recording").json()["recording"] is not None:
            client.post("/api/recording/stop")
        client.put("/api/measure/tool", json={"measurements": []})
