"""Recording the live simulator over REST: start, sets with depth, list, zip, export, delete."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import tifffile
from fastapi.testclient import TestClient

from app.capture.captureset import read_capture_set
from app.main import create_app
from tests.api.conftest import live_settings, wait_for

TOKEN = "rec-token-123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def test_record_live_session(tmp_path: Path, sim_calibration_file: Path) -> None:
    # 40 ms: sets stay whole on a busy 2-core machine (the camera buffer outlasts a reconstruction)
    settings = live_settings(tmp_path, sim_calibration_file, api_token=TOKEN, exposure_ms=40.0)
    with TestClient(create_app(settings)) as client:
        assert client.get("/api/status").status_code == 401  # issue 16: reads need the token too
        assert client.post("/api/login", headers=AUTH).status_code == 200  # session cookie for reads
        wait_for(client, lambda s: s["results_published"] >= 1, 120, "first result")
        assert client.post("/api/recording/start", json={"name": "op-1"}).status_code == 401
        r = client.post("/api/recording/start", json={"name": "op-1"}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert r.json()["recording"] == "op-1"
        assert client.get("/api/status").json()["recording"] == "op-1"
        r = client.post("/api/recording/start", json={"name": "op-2"}, headers=AUTH)
        assert r.status_code == 409 and "already recording" in r.json()["detail"]
        assert client.delete("/api/recordings/op-1", headers=AUTH).status_code == 409
        wait_for(client, lambda s: client.get("/api/recording").json()["sets_with_depth"] >= 3, 60,
                 "three recorded sets with depth")
        r = client.post("/api/recording/stop", headers=AUTH)
        assert r.status_code == 200
        session = r.json()["stopped"]
        assert session["name"] == "op-1" and session["stopped"] is not None
        assert "api_token" not in session["settings"]  # the secret never reaches the disk
        assert client.get("/api/status").json()["recording"] is None
        assert client.post("/api/recording/stop", headers=AUTH).json() == {"recording": None, "stopped": None}

        # what is on disk is whole capture sets, consecutive frames, depth maps of the right shape
        root = Path(settings.data_dir) / "recordings" / "op-1"
        sets = session["sets"]
        assert len(sets) >= 3
        with_depth = [s for s in sets if s["depth"]]
        assert len(with_depth) >= 3
        for s in with_depth[:3]:
            cap = read_capture_set(root / s["folder"])
            idx = cap.extra["frame_indices"]
            assert idx == list(range(idx[0], idx[0] + 16)) and cap.frames.dtype == np.uint8
            depth = np.load(root / s["folder"] / "depth.npy")
            assert depth.shape == cap.frames.shape[1:] and depth.dtype == np.float32
            assert np.isfinite(depth).mean() > 0.2 and np.nanmax(depth) < 40

        listed = client.get("/api/recordings").json()
        assert [x["name"] for x in listed] == ["op-1"] and listed[0]["n_sets"] == len(sets)
        meta = client.get("/api/recordings/op-1").json()
        assert meta["sets"] == sets

        r = client.get("/api/recordings/op-1.zip")
        assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
        zf = zipfile.ZipFile(io.BytesIO(r.content))
        assert zf.testzip() is None
        assert f"op-1/{sets[0]['folder']}/frame_15.png" in zf.namelist()

        index = int(with_depth[0]["folder"][4:])
        r = client.get(f"/api/recordings/op-1/sets/{index}/depth?format=tiff")
        assert r.status_code == 200 and r.headers["content-type"] == "image/tiff"
        tiff = tifffile.imread(io.BytesIO(r.content))
        np.testing.assert_array_equal(tiff, np.load(root / with_depth[0]["folder"] / "depth.npy"))
        assert client.get(f"/api/recordings/op-1/sets/{len(sets) + 5}/depth").status_code == 404

        r = client.get("/api/depth/latest?format=tiff")
        assert r.status_code == 200
        live_depth = tifffile.imread(io.BytesIO(r.content))
        assert live_depth.dtype == np.float32 and live_depth.ndim == 2

        # names that would escape the data folder are refused before touching the disk
        for bad in ("..", ".hidden", "a b", "x" * 65):
            r = client.post("/api/recording/start", json={"name": bad}, headers=AUTH)
            assert r.status_code == 422 and r.json()["detail"]
        assert client.get("/api/recordings/..%2F..%2Fetc").status_code in (404, 422)
        assert client.get("/api/recordings/nope").status_code == 404
        assert client.get("/api/recordings/nope.zip").status_code == 404

        r = client.delete("/api/recordings/op-1", headers=AUTH)
        assert r.status_code == 200 and not root.exists()
        assert client.get("/api/recordings").json() == []
