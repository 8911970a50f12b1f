"""The change reference and the live change map through the real app on the twin."""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.calib import save_calibration
from app.core.schedule import PatternSchedule
from app.devices.sim import default_rig
from app.devices.sim.ideal import ideal_calibration
from app.main import create_app
from tests.helpers.live_app import live_settings, wait_for


@pytest.fixture(scope="module")
def twin_calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The twin's exact (oracle) calibration: no start-up calibration needed."""
    path = tmp_path_factory.mktemp("cal") / "twin.json"
    save_calibration(ideal_calibration(default_rig(), PatternSchedule()), path)
    return path


def _client(data: Path, cal: Path) -> TestClient:
    return TestClient(create_app(live_settings(data, cal, sim_scene="tissue_still")))


def _npy(resp) -> np.ndarray:
    assert resp.status_code == 200, resp.text
    return np.load(io.BytesIO(resp.content))


def _one_map(client, fields: tuple[str, ...]) -> list[np.ndarray]:
    """The fields of one change map: a new map may be published between the requests (its
    seq is in each response), so ask again until all came from the same one."""
    for _ in range(20):
        resps = [client.get(f"/api/change/latest?format=npy&field={f}") for f in fields]
        if len({r.headers["X-Fringescope-Seq"] for r in resps}) == 1:
            return [_npy(r) for r in resps]
    raise AssertionError("no two requests in a row answered from the same change map")


def _wait_change(client: TestClient, after_seq: int, timeout_s: float = 120) -> dict:
    deadline = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < deadline:
        last = client.get("/api/change/summary")
        if last.status_code == 200 and last.json()["seq"] > after_seq:
            return last.json()
        time.sleep(0.2)
    raise AssertionError(f"no change map after seq {after_seq}: {last and last.text}")


def test_reference_and_change_map_live_and_across_a_restart(tmp_path, twin_calibration):
    data = tmp_path / "run"
    with _client(data, twin_calibration) as client:
        assert client.get("/api/reference").status_code == 404
        r = client.get("/api/change/latest")
        assert r.status_code == 404 and "no reference" in r.json()["detail"]
        wait_for(client, lambda st: st["results_published"] >= 1, 300, "a depth map")
        r = client.post("/api/reference")
        assert r.status_code == 200, r.text
        ref = r.json()
        assert ref["source"]["kind"] == "live" and ref["valid_share"] > 0.5
        assert ref["image_size"] == [1384, 1032]
        assert client.get("/api/reference").json() == ref
        summary = _wait_change(client, ref["source"]["seq"])
        # a still scene: nothing changed beyond the stated rate, compared pixel by pixel
        assert summary["mode"] == "fixed" and summary["registration"] is None
        assert summary["changed_share"] <= 1e-3
        assert summary["compared_pixels"] > 0.5 * 1384 * 1032
        delta, sigma, sig, changed = _one_map(client, ("delta", "sigma", "significance",
                                                       "changed"))
        assert delta.shape == (1032, 1384) and delta.dtype == np.float32
        assert changed.dtype == bool and sigma.dtype == sig.dtype == np.float32
        ok = np.isfinite(delta)
        assert np.sqrt(np.mean(delta[ok] ** 2)) <= 1.2 * np.sqrt(np.mean(sigma[ok] ** 2))
        for fmt in ("png", "color"):
            r = client.get(f"/api/change/latest?format={fmt}&range_mm=0.5")
            assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n"
        assert client.get("/api/change/latest?format=png&field=sigma").status_code == 200
        r = client.get("/api/change/latest?format=png&field=changed")
        assert r.status_code == 422 and "npy only" in r.json()["detail"]
        assert client.get("/api/change/latest?range_mm=0").status_code == 422
    # the reference is on disk: a restarted service still has it
    with _client(data, twin_calibration) as client:
        assert client.get("/api/reference").json() == ref
        wait_for(client, lambda st: st["results_published"] >= 1, 300, "a depth map")
        assert _wait_change(client, 0)["mode"] == "fixed"
        assert client.delete("/api/reference").status_code == 204
        assert client.delete("/api/reference").status_code == 404
        assert client.get("/api/reference").status_code == 404
    assert not (data / "data" / "reference" / "reference.npz").exists()
    assert not (data / "data" / "reference" / "reference.json").exists()


def test_bad_reference_requests_are_refused_with_reasons(tmp_path, twin_calibration):
    data = tmp_path / "bad"
    with _client(data, twin_calibration) as client:
        for body, code, words in (
            ({"recording": "x"}, 422, "both recording and index"),
            ({"foo": 1}, 422, "body"),
            ({"recording": "../etc", "index": 0}, 422, "recording"),
            ({"recording": "nope", "index": 0}, 404, "no recording"),
        ):
            r = client.post("/api/reference", json=body)
            assert r.status_code == code, (body, r.text)
            assert words in r.json()["detail"]
        r = client.post("/api/reference", content=b"{not json",
                        headers={"content-type": "application/json"})
        assert r.status_code == 422
        # a reference taken with another calibration: 409 with the reason, nothing shown
        wait_for(client, lambda st: st["results_published"] >= 1, 300, "a depth map")
        assert client.post("/api/reference").status_code == 200
    npz_path = data / "data" / "reference" / "reference.npz"
    with np.load(npz_path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    meta["calibration"] = "2020-01-01T00:00:00"
    arrays["meta"] = np.array(json.dumps(meta))
    with open(npz_path, "wb") as f:
        np.savez(f, **arrays)
    with _client(data, twin_calibration) as client:
        wait_for(client, lambda st: st["results_published"] >= 2, 300, "depth maps")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            r = client.get("/api/change/latest")
            if r.status_code == 409 and "calibration" in r.json()["detail"]:
                break
            time.sleep(0.2)
        assert r.status_code == 409 and "set a new reference" in r.json()["detail"]


def test_recordings_and_openigtlink_carry_the_change_map(tmp_path, twin_calibration):
    import pyigtl

    settings = live_settings(tmp_path / "out", twin_calibration, sim_scene="tissue_still",
                             igtl_port=0)
    app = create_app(settings)
    with TestClient(app) as client:
        wait_for(client, lambda st: st["results_published"] >= 1, 300, "a depth map")
        assert client.post("/api/reference").status_code == 200
        _wait_change(client, 0)
        igtl = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=app.state.igtl.port)
        try:
            msg = igtl.wait_for_message("FringescopeChange", timeout=60)
        finally:
            igtl.stop()
        assert msg is not None
        image = np.asarray(msg.image)
        assert image.dtype == np.float32 and image.size == 1384 * 1032
        assert np.isfinite(image).mean() > 0.5 and np.nanmax(np.abs(image)) < 2.0
        published = client.get("/api/status").json()["results_published"]
        r = client.post("/api/recording/start", json={"name": "withref"})
        assert r.status_code == 200, r.text
        # maps made while the recording runs (the count before it may already be high)
        wait_for(client, lambda st: st["results_published"] >= published + 4, 300, "more maps")
        client.post("/api/recording/stop")
    rec = tmp_path / "out" / "data" / "recordings" / "withref"
    session = json.loads((rec / "session.json").read_text())
    with_depth = [s for s in session["sets"] if s.get("depth")]
    with_change = [s for s in with_depth if (rec / s["folder"] / "change.npy").is_file()]
    assert with_depth and len(with_change) >= len(with_depth) - 1  # the last may be cut off
    delta = np.load(rec / with_change[0]["folder"] / "change.npy")
    assert delta.dtype == np.float32 and delta.shape == (1032, 1384)
    assert with_change[0]["change"] == "fixed"
