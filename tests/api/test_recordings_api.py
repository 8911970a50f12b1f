"""Recording the live simulator over REST: start, sets with depth, list, zip, export, delete."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import tifffile
from fastapi.testclient import TestClient

from app.capture.captureset import read_capture_set
from app.main import create_app
from app.service.framesets import MAX_SPAN_CYCLES
from tests.helpers.live_app import live_settings, wait_for
from tests.helpers.served import ServedApp, free_port

TOKEN = "rec-token-123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def test_record_live_session(tmp_path: Path, sim_calibration_file: Path) -> None:
    # 40 ms: sets stay whole on a busy 2-core machine (the camera buffer outlasts a reconstruction)
    settings = live_settings(tmp_path, sim_calibration_file, api_token=TOKEN, exposure_ms=40.0)
    with TestClient(create_app(settings)) as client:
        assert client.get("/api/status").status_code == 401  # reads need the token too
        # a session cookie for reads
        assert client.post("/api/login", headers=AUTH).status_code == 200
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
        stopped = client.post("/api/recording/stop", headers=AUTH).json()
        assert stopped == {"recording": None, "stopped": None}

        # what is on disk is whole capture sets of gap-free groups, depth maps of the right shape
        root = Path(settings.data_dir) / "recordings" / "op-1"
        sets = session["sets"]
        assert len(sets) >= 3
        with_depth = [s for s in sets if s["depth"]]
        assert len(with_depth) >= 3
        for s in with_depth[:3]:
            cap = read_capture_set(root / s["folder"])
            idx = cap.extra["frame_indices"]
            # each frequency group is 4 consecutive frames; a group lost to a dropped frame is
            # patched from a cycle at most 3 back, so the groups need not follow each other
            groups = [idx[g: g + 4] for g in range(0, 16, 4)]
            assert all(grp == list(range(grp[0], grp[0] + 4)) for grp in groups), idx
            assert max(idx) - min(idx) < 3 * 16 and cap.frames.dtype == np.uint8
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
        assert f"op-1/{sets[0]['folder']}/frame_15.npy.zst" in zf.namelist()

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


def _serve(tmp_path: Path, calibration: Path, port: int, *wrap: str,
           **env_extra: str) -> ServedApp:
    """``fringescope serve`` as its own process (optionally under ``wrap``, e.g. unshare)."""
    env = dict(os.environ, FRINGESCOPE_CALIBRATION_FILE=str(calibration),
               FRINGESCOPE_VIEWER="false", FRINGESCOPE_SIM_SCENE="dof_target",
               FRINGESCOPE_SIM_SEED="1", FRINGESCOPE_EXPOSURE_MS="30",
               FRINGESCOPE_SCHEDULE="geometric-9", NUMBA_THREADING_LAYER="workqueue", **env_extra)
    args = ["--port", str(port), "--data-dir", str(tmp_path / "data")]
    return ServedApp(args, env, tmp_path / f"server-{port}-{time.monotonic_ns()}.log", wrap)


def _poll(url: str, server: ServedApp, predicate: Callable[[Any], bool], timeout_s: float,
          what: str) -> Any:
    deadline, body = time.monotonic() + timeout_s, None
    while time.monotonic() < deadline:
        if not server.running():
            raise AssertionError(f"server exited {server.proc.returncode} waiting for {what}: "
                                 f"{server.log()}")
        try:
            body = httpx.get(url, timeout=5).json()
            if predicate(body):
                return body
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise AssertionError(f"timed out waiting for {what}; last answer: {body}")


def test_killed_server_leaves_an_interrupted_recording_of_whole_sets(
        tmp_path: Path, sim_calibration_file: Path) -> None:
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = _serve(tmp_path, sim_calibration_file, port)
    try:
        _poll(base + "/api/status", server, lambda s: s["results_published"] >= 1, 180,
              "first depth map")
        r = httpx.post(base + "/api/recording/start", json={"name": "crashed"}, timeout=10)
        assert r.status_code == 200, r.text
        _poll(base + "/api/recording", server, lambda s: s["sets_with_depth"] >= 4, 120,
              "four recorded sets")
        os.kill(server.pid, signal.SIGKILL)  # mid-recording: the writer is busy with the next set
        server.proc.wait(timeout=30)
    finally:
        if server.running():
            server.proc.kill()
            server.proc.wait()
    root = tmp_path / "data" / "recordings" / "crashed"
    before = json.loads((root / "session.json").read_text())
    assert before["stopped"] is None and "interrupted" not in before  # what the crash left

    server = _serve(tmp_path, sim_calibration_file, port)
    try:
        listed = _poll(base + "/api/recordings", server, lambda x: isinstance(x, list), 180,
                       "the listing")
        (summary,) = listed
        assert summary["name"] == "crashed" and summary["interrupted"] is True
        meta = httpx.get(base + "/api/recordings/crashed", timeout=10).json()
        sets = meta["sets"]
        assert summary["n_sets"] == len(sets) >= 4
        assert meta["interrupted"] is True and meta["stopped"] == sets[-1]["timestamp"]
        assert not [p.name for p in root.iterdir() if p.name.startswith(".")]  # partials gone
        assert sorted(p.name for p in root.iterdir() if p.is_dir()) == [s["folder"] for s in sets]
        for s in sets:  # every listed set reads back whole
            cap = read_capture_set(root / s["folder"])
            idx = cap.extra["frame_indices"]
            assert cap.frames.shape[0] == 9
            # whole frequency groups (3 consecutive frames each); a group lost to a dropped
            # frame is stood in for by an earlier cycle's copy (framesets.MAX_SPAN_CYCLES)
            for g in range(3):
                assert idx[3 * g:3 * g + 3] == list(range(idx[3 * g], idx[3 * g] + 3)), idx
            assert max(idx) - min(idx) < MAX_SPAN_CYCLES * 9, idx
            assert all(f.endswith(".npy.zst") for f in s["files"] if f.startswith("frame_"))
            if s["depth"]:
                depth = np.load(root / s["folder"] / "depth.npy")
                assert depth.shape == cap.frames.shape[1:] and np.isfinite(depth).mean() > 0.2
        r = httpx.post(base + "/api/recording/start", json={"name": "crashed"}, timeout=10)
        assert r.status_code == 409  # the interrupted recording is kept under its name
    finally:
        server.stop()


def _can_mount_tmpfs(tmp_path: Path) -> bool:
    probe = tmp_path / "probe"
    probe.mkdir()
    r = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=1m tmpfs {probe}"],
                       capture_output=True, timeout=30)
    return r.returncode == 0


def test_a_full_disk_stops_the_recording_with_the_reason_in_status(
        tmp_path: Path, sim_calibration_file: Path) -> None:
    """A real ENOSPC: the server runs in its own mount namespace on a 40 MB tmpfs data folder."""
    if not _can_mount_tmpfs(tmp_path):
        pytest.skip("no user/mount namespaces here (unshare -rm): no small disk for the server")
    data = tmp_path / "data"
    data.mkdir()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    mount = f'mount -t tmpfs -o size=40m tmpfs {data} && exec "$@"'
    wrap = ("unshare", "-rm", "sh", "-c", mount, "sh")
    server = _serve(tmp_path, sim_calibration_file, port, *wrap,
                    FRINGESCOPE_RECORDING_MIN_FREE_MB="0")
    try:
        _poll(base + "/api/status", server, lambda s: s["results_published"] >= 1, 180,
              "first depth map")
        r = httpx.post(base + "/api/recording/start", json={"name": "full"}, timeout=10)
        assert r.status_code == 200, r.text
        st = _poll(base + "/api/status", server, lambda s: s["recording"] is None, 120,
                   "the recording to stop")
        (warning,) = [w for w in st["warnings"] if "recording 'full' stopped" in w]
        assert "disk full" in warning and "No space left on device" in warning, warning
        rec = httpx.get(base + "/api/recording", timeout=10).json()
        assert rec["recording"] is None and rec["last_error"] == warning and rec["errors"] == 1
        (summary,) = httpx.get(base + "/api/recordings", timeout=10).json()
        assert summary["name"] == "full" and summary["stopped"] is not None
        assert not summary["interrupted"]
        meta = httpx.get(base + "/api/recordings/full", timeout=10).json()
        assert 1 <= summary["n_sets"] == len(meta["sets"]) < 8  # ~11 MB a set on 40 MB
        # the service goes on: depth keeps coming; the warning stays until a new recording starts
        seq = httpx.get(base + "/api/status", timeout=10).json()["results_published"]
        st = _poll(base + "/api/status", server, lambda s: s["results_published"] > seq + 2, 60,
                   "more depth")
        assert warning in st["warnings"] and st["state"] == "running"
        httpx.delete(base + "/api/recordings/full", timeout=10)
        r = httpx.post(base + "/api/recording/start", json={"name": "again"}, timeout=10)
        assert r.status_code == 200, r.text
        assert warning not in httpx.get(base + "/api/status", timeout=10).json()["warnings"]
        httpx.post(base + "/api/recording/stop", timeout=30)
    finally:
        server.stop()
