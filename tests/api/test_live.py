"""The running app on the simulator: status, controls reaching the frames, results, streams."""

from __future__ import annotations

import io
import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.helpers.live_app import LIVE_EXPOSURE_MS, wait_for, wait_result

STATUS_KEYS = {
    "state", "camera_fps", "depth_fps", "latency_ms", "exposure_ms", "led", "mode", "calibration",
    "devices", "last_error", "sets_completed", "dropped_sets", "incomplete_sets", "frames_dropped",
    "faults", "warnings", "state_reason", "phase", "progress", "set_period_s", "last_depth_age_s",
    "last_error_at", "last_error_resolved", "groups_lost", "patched_sets", "warmup", "since_warmup",
    "calibration_session",
}


def test_status_reports_a_running_instrument(live: TestClient) -> None:
    st = wait_for(live, lambda s: s["state"] == "running" and s["depth_fps"] > 0, 30, "running")
    assert st.keys() >= STATUS_KEYS
    assert st["mode"] == "set" and st["exposure_ms"] == LIVE_EXPOSURE_MS and st["led"] == "green"
    assert st["camera_fps"] > 5 and st["latency_ms"] is not None and st["latency_ms"] > 0
    assert st["calibration"]["name"] == "sim" and st["calibration"]["height_range_mm"][1] > 10
    assert {d["kind"] for d in st["devices"]} >= {"camera", "projector"}
    assert all(d["state"] in ("open", "running") for d in st["devices"])
    # running: a map within 2 set periods (16 frames at the 30 ms exposure), nothing to explain
    assert st["state_reason"] is None and st["phase"] is None and st["progress"] is None
    assert st["set_period_s"] == pytest.approx(16 * LIVE_EXPOSURE_MS / 1000, rel=0.3)
    assert 0 <= st["last_depth_age_s"] <= 2 * st["set_period_s"]
    assert st["warmup"]["frames_received"] >= 16
    assert st["since_warmup"].keys() == st["warmup"].keys()
    # over a few seconds: one depth map per whole set at most (bounded by the camera)
    time.sleep(3.0)
    s1 = live.get("/api/status").json()
    sets = s1["sets_completed"] - st["sets_completed"]
    results = s1["results_published"] - st["results_published"]
    assert sets >= 2 and 1 <= results <= sets + 1
    assert s1["frames_received"] - st["frames_received"] >= 16 * sets


def test_the_live_engine_uses_the_cameras_measured_noise(live: TestClient) -> None:
    st = wait_for(live, lambda s: s["sensor_noise"]["source"] == "measured", 30, "a noise estimate")
    noise = st["sensor_noise"]
    # the simulated camera is SensorNoise.typical(255): read noise 12 e- at 16000 e- full well
    # (0.19 DN; with quantisation, (0.19^2 + 1/12)^0.5 = 0.35 DN), gain 255/16000 DN/e-
    assert noise["gain_dn_per_e"] == pytest.approx(255 / 16000, rel=0.15)
    assert 0.2 < noise["read_noise_dn"] < 0.6 and noise["estimates"] >= 1
    inst = live.app.state.instrument  # type: ignore[attr-defined]
    seq0 = inst.results.latest()[0]
    seq, res = inst.results.wait_newer(seq0, 10)  # a map made after the estimate
    # passed to the engine with every set (σ, the validity rule, the motion test), not installed in
    # it
    assert res is not None and res.noise is inst.pipeline.reconstruction.noise.current
    # the twin's projector is sinusoidal: its sets measure no gamma, the maps are not corrected
    noise = live.get("/api/status").json()["sensor_noise"]
    assert noise["phase_error"] == "none" == res.phase_error_source
    assert noise["gamma_table_rms_rad"] is None


def test_exposure_and_led_reach_the_frames(live: TestClient) -> None:
    try:
        r = live.put("/api/exposure", json={"exposure_ms": 14.5})
        assert r.status_code == 200 and r.json()["exposure_ms"] == 14.5
        meta = wait_result(
            live, lambda m: m["exposure_ms"] == 14.5, 20, "exposure 14.5 in the frames"
        )
        assert len(meta["frame_indices"]) == 16
        r = live.put("/api/led", json={"led": "red"})
        assert r.status_code == 200
        wait_result(live, lambda m: m["led"] == "red", 20, "red LED in the frames")
        st = live.get("/api/status").json()
        assert st["led"] == "red" and st["exposure_ms"] == 14.5
    finally:
        live.put("/api/exposure", json={"exposure_ms": LIVE_EXPOSURE_MS})
        live.put("/api/led", json={"led": "green"})
    wait_result(live, lambda m: m["led"] == "green" and m["exposure_ms"] == LIVE_EXPOSURE_MS, 20)


@pytest.mark.parametrize(
    "method, path, body",
    [
        ("put", "/api/exposure", {"exposure_ms": 0.5}),
        ("put", "/api/exposure", {"exposure_ms": 100.5}),
        ("put", "/api/exposure", {"exposure_ms": "fast"}),
        ("put", "/api/exposure", {}),
        ("put", "/api/exposure", {"exposure_ms": 20, "gain": 2}),
        ("put", "/api/led", {"led": "purple"}),
        ("put", "/api/led", {"led": 1}),
        ("put", "/api/mode", {"rolling": "yes"}),
        ("post", "/api/exposure/auto", {"saturation_limit": 2}),
        ("post", "/api/analysis/plane", {"roi": [10, 10, 5, 20]}),
        ("post", "/api/analysis/plane", {"roi": [1, 2, 3]}),
        ("post", "/api/analysis/feature", {"roi": "all"}),
        ("post", "/api/calibration/session", {"type": "hexagons"}),
        (
            "post",
            "/api/calibration/session",
            {"type": "checkerboard", "inner_corners": [1, 6], "square_mm": 2},
        ),
        ("post", "/api/calibration/session", {"type": "checkerboard", "inner_corners": [8, 6]}),
    ],
)
def test_bad_input_is_422_with_a_reason(
    live: TestClient, method: str, path: str, body: object
) -> None:
    r = getattr(live, method)(path, json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"]


def test_malformed_json_is_422(live: TestClient) -> None:
    r = live.put(
        "/api/exposure", content=b"{not json", headers={"content-type": "application/json"}
    )
    assert r.status_code == 422 and r.json()["detail"]


@pytest.mark.parametrize(
    "query", ["format=bmp", "format=color&min_mm=10&max_mm=5", "format=color&min_mm=nan"]
)
def test_bad_depth_query_is_422(live: TestClient, query: str) -> None:
    r = live.get(f"/api/depth/latest?{query}")
    assert r.status_code == 422 and r.json()["detail"]


def test_depth_formats_agree(live: TestClient) -> None:
    r = live.get("/api/depth/latest?format=npy")
    assert r.status_code == 200
    depth = np.load(io.BytesIO(r.content))
    seq = int(r.headers["x-fringescope-seq"])
    assert depth.dtype == np.float32 and depth.ndim == 2
    valid = np.isfinite(depth)
    assert valid.mean() > 0.3
    # the same result again (pinned by seq) as a 16-bit µm PNG
    for _ in range(50):
        r = live.get("/api/depth/latest?format=png")
        if int(r.headers["x-fringescope-seq"]) == seq:
            break
        r = live.get("/api/depth/latest?format=npy")
        depth, seq = np.load(io.BytesIO(r.content)), int(r.headers["x-fringescope-seq"])
        valid = np.isfinite(depth)
    png = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.shape == depth.shape
    assert np.array_equal(png == 0, ~valid)
    expect = np.clip(np.rint(depth[valid] * 1000), 1, 65535)
    assert np.abs(png[valid].astype(np.int64) - expect).max() <= 1
    r = live.get("/api/depth/latest?format=color&min_mm=0&max_mm=20")
    color = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    # image + colour bar
    assert color.shape[0] >= depth.shape[0] and color.shape[1] > depth.shape[1]


def test_sigma_field_matches_depth(live: TestClient) -> None:
    for _ in range(50):
        d = live.get("/api/depth/latest?format=npy")
        s = live.get("/api/depth/latest?format=npy&field=sigma")
        if d.headers["x-fringescope-seq"] == s.headers["x-fringescope-seq"]:
            break
    depth, sigma = np.load(io.BytesIO(d.content)), np.load(io.BytesIO(s.content))
    assert sigma.dtype == np.float32 and sigma.shape == depth.shape
    assert np.array_equal(np.isfinite(sigma), np.isfinite(depth))
    assert 0.0 < np.nanmedian(sigma) < 0.5
    r = live.get("/api/depth/latest?format=color&field=sigma")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert live.get("/api/depth/latest?field=noise").status_code == 422
    ply = live.get("/api/pointcloud/latest.ply")
    assert b"property float sigma_mm" in ply.content[:400]


def test_sigma_parts_of_the_live_result(live: TestClient) -> None:
    """σ (total) = σ_noise ⊕ σ_model on one published result; both parts in the PLY too."""
    for _ in range(50):
        got = {f: live.get(f"/api/depth/latest?format=npy&field={f}")
               for f in ("sigma", "sigma_noise", "sigma_model")}
        if len({r.headers["x-fringescope-seq"] for r in got.values()}) == 1:
            break
    sig, noise, model = (np.load(io.BytesIO(got[f].content)).astype(np.float64)
                         for f in ("sigma", "sigma_noise", "sigma_model"))
    ok = np.isfinite(sig)
    assert (
        ok.any()
        and np.array_equal(ok, np.isfinite(model))
        and np.array_equal(ok, np.isfinite(noise))
    )
    np.testing.assert_allclose(sig[ok] ** 2, noise[ok] ** 2 + model[ok] ** 2, rtol=1e-4)
    assert np.median(model[ok]) > 0.0  # the simulator's calibration carries its jackknife
    assert live.get("/api/depth/latest?format=color&field=sigma_model").status_code == 200
    head = live.get("/api/pointcloud/latest.ply").content[:600]
    assert b"property float sigma_noise_mm" in head and b"property float sigma_model_mm" in head


def test_texture_reason_and_pointcloud(live: TestClient) -> None:
    tex = live.get("/api/texture/latest.png")
    assert tex.status_code == 200 and tex.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(tex.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.ndim == 2 and img.std() > 5
    reason = live.get("/api/reason/latest.png")
    assert reason.status_code == 200 and "ok" in reason.headers["x-fringescope-reasons"]
    ply = live.get("/api/pointcloud/latest.ply")
    assert ply.status_code == 200
    head = ply.content[:400].decode("ascii", "replace")
    assert head.startswith("ply") and "element vertex" in head
    n = int(head.split("element vertex")[1].split()[0])
    meta = live.get("/api/result/latest").json()
    h, w = meta["shape"]
    assert 0 < n <= h * w
    # a still scene: the raw motion flags stay at the still rate, so no moving-scene σ bound was
    # applied
    assert meta["scene_moved"] is False and meta["uncertain_moving_pixels"] == 0
    assert n == pytest.approx(meta["valid_fraction"] * h * w, rel=0.2)


def test_websocket_stream_delivers_new_jpegs(live: TestClient) -> None:
    with live.websocket_connect("/api/stream/depth?min_mm=0&max_mm=30") as ws:
        first = ws.receive_bytes()
        second = ws.receive_bytes()
    for data in (first, second):
        assert data[:2] == b"\xff\xd8"  # JPEG
        assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) is not None


def test_mjpeg_stream_parts(live: TestClient) -> None:
    r = live.get("/api/stream/depth.mjpeg?frames=2")
    assert r.headers["content-type"].startswith("multipart/x-mixed-replace")
    parts = [p for p in r.content.split(b"--frame") if b"Content-Type: image/jpeg" in p]
    assert len(parts) == 2
    jpegs = [p.split(b"\r\n\r\n", 1)[1] for p in parts]
    assert all(j.startswith(b"\xff\xd8") for j in jpegs)


def test_rolling_mode_labels_results(live: TestClient) -> None:
    try:
        assert live.put("/api/mode", json={"rolling": True}).json() == {"mode": "rolling",
                                                                          "bracket": False}
        meta = wait_result(live, lambda m: m["mode"] == "rolling", 20, "a rolling result")
        windows = [meta["frame_indices"]]
        while len(windows) < 4:
            seq = meta["seq"]
            meta = wait_result(
                live, lambda m, seq=seq: m["seq"] > seq, 10, "the next rolling result"
            )
            assert meta["mode"] == "rolling"
            windows.append(meta["frame_indices"])
        for idx in windows:  # always the last 16 consecutive frames, in capture-set order
            assert sorted(idx) == list(range(min(idx), min(idx) + 16))
        # windows that start mid-sequence wrap around (frames listed by pattern index)
        assert any(idx != sorted(idx) for idx in windows)
        assert live.get("/api/status").json()["mode"] == "rolling"
    finally:
        live.put("/api/mode", json={"rolling": False})
    wait_result(live, lambda m: m["mode"] == "set", 20)


def test_acquisition_stop_and_start(live: TestClient) -> None:
    assert live.post("/api/acquisition/stop").json()["acquiring"] is False
    st = wait_for(live, lambda s: s["state"] == "stopped", 10, "stopped")
    assert "acquisition stopped" in st["state_reason"]
    time.sleep(0.5)
    frames = live.get("/api/status").json()["frames_received"]
    time.sleep(0.5)
    assert live.get("/api/status").json()["frames_received"] == frames  # the camera really stopped
    assert live.post("/api/acquisition/start").json()["acquiring"] is True
    wait_for(
        live,
        lambda s: s["state"] == "running" and s["frames_received"] > frames + 16,
        30,
        "running again",
    )


def test_calibration_file_round_trip_and_validation(live: TestClient) -> None:
    r = live.get("/api/calibration/file")
    assert r.status_code == 200
    data = r.json()
    assert data["format"] == "fringescope.calibration/2"
    summary = live.get("/api/calibration").json()
    assert summary["model"] == data["model"]["name"] and set(summary["held_out"]) <= {
        "eq5",
        "geometric",
    }
    other = "eq5" if data["model"]["name"] == "geometric" else "geometric"
    # one model's numbers under the other's name
    corrupted = dict(data, model=dict(data["model"], name=other))
    r = live.put("/api/calibration/file", json=corrupted)
    assert r.status_code == 422 and "model" in r.json()["detail"] and "\n" not in r.json()["detail"]
    bad = dict(data, format="something/9")
    r = live.put("/api/calibration/file", json=bad)
    assert r.status_code == 422 and "format" in r.json()["detail"]
    wrong_size = dict(data, image_size=[640, 480])
    r = live.put("/api/calibration/file", json=wrong_size)
    assert r.status_code == 422 and "image size" in r.json()["detail"]
    r = live.put(
        "/api/calibration/file", content=b"[1, 2", headers={"content-type": "application/json"}
    )
    assert r.status_code == 422
    r = live.put("/api/calibration/file", json=data)
    assert r.status_code == 200 and r.json()["name"] == "uploaded"
    assert live.get("/api/calibration").json()["name"] == "uploaded"
    wait_for(live, lambda s: s["results_published"] > 0 and s["state"] == "running", 20)


def test_plane_analysis_in_an_roi(live: TestClient) -> None:
    meta = wait_result(live, lambda m: True, 30)
    h, w = meta["shape"]
    r = live.post("/api/analysis/plane", json={"roi": [w // 3, h // 3, 2 * w // 3, 2 * h // 3]})
    assert r.status_code in (200, 422), r.text
    if r.status_code == 200:
        body = r.json()
        assert (
            body["points"] > 10 and body["precision_mm"] is not None and body["precision_mm"] >= 0
        )
    r = live.post("/api/analysis/plane", json={"roi": [0, 0, w + 10, h + 10]})
    assert r.status_code == 422 and "roi" in r.json()["detail"]


def test_openapi_lists_the_fixed_routes(live: TestClient) -> None:
    paths = live.get("/openapi.json").json()["paths"]
    for p in (
        "/api/status",
        "/api/exposure",
        "/api/led",
        "/api/acquisition/start",
        "/api/acquisition/stop",
        "/api/depth/latest",
        "/api/pointcloud/latest.ply",
        "/api/reconstruct",
        "/api/calibration/file",
    ):
        assert p in paths
    assert live.get("/docs").status_code == 200
