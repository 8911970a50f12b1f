"""POST /api/reconstruct: capture sets uploaded as files or a zip, checked against the truth."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.capture.captureset import write_capture_set
from app.main import create_app
from tests.helpers.live_app import live_settings


@pytest.fixture(scope="module")
def dof_set(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    from app.devices.sim import render_capture_set

    capture, truth_depth, _ = render_capture_set("dof_target", seed=3)
    folder = write_capture_set(tmp_path_factory.mktemp("dof") / "set", capture)
    return folder, np.asarray(truth_depth)


def _files(folder: Path) -> list[tuple[str, tuple[str, bytes, str]]]:
    out = []
    for p in sorted(folder.iterdir()):
        ctype = "application/json" if p.suffix == ".json" else "image/png"
        out.append(("files", (p.name, p.read_bytes(), ctype)))
    return out


def _zip(folder: Path, prefix: str = "set/") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(folder.iterdir()):
            zf.writestr(prefix + p.name, p.read_bytes())
    return buf.getvalue()


def test_multipart_upload_reconstructs_the_dof_target(live: TestClient, dof_set: tuple[Path, np.ndarray]) -> None:
    folder, truth = dof_set
    r = live.post("/api/reconstruct", files=_files(folder))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["shape"] == list(truth.shape) and body["valid_fraction"] > 0.3
    lo, hi = np.nanpercentile(truth, [1, 99])
    assert body["height_min_mm"] < lo + 1.0 and body["height_max_mm"] > hi - 1.0
    r = live.post("/api/reconstruct?format=npy", files=_files(folder))
    depth = np.load(io.BytesIO(r.content))
    both = np.isfinite(depth) & np.isfinite(truth)
    assert both.mean() > 0.3
    err = depth[both] - truth[both]
    assert np.mean(np.abs(err)) < 0.15, f"mean |error| {np.mean(np.abs(err)):.3f} mm"


def test_zip_upload_as_file_and_as_body(live: TestClient, dof_set: tuple[Path, np.ndarray]) -> None:
    folder, _ = dof_set
    data = _zip(folder)
    a = live.post("/api/reconstruct", files=[("file", ("set.zip", data, "application/zip"))])
    b = live.post("/api/reconstruct", content=data, headers={"content-type": "application/zip"})
    assert a.status_code == b.status_code == 200
    assert a.json()["valid_fraction"] == b.json()["valid_fraction"] > 0.3


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda files: [f for f in files if f[1][0] != "capture.json"], "capture.json"),
        (lambda files: [f for f in files if f[1][0] != "frame_07.png"], "frame_07.png"),
        (lambda files: [(k, (n, b"not a png", t)) if n == "frame_03.png" else (k, (n, b, t))
                        for k, (n, b, t) in files], "frame_03.png"),
        (lambda files: [(k, (n, b"{", t)) if n == "capture.json" else (k, (n, b, t))
                        for k, (n, b, t) in files], "capture.json"),
    ],
)
def test_broken_uploads_are_422_naming_the_file(live: TestClient, dof_set: tuple[Path, np.ndarray],
                                                mutate, message: str) -> None:
    folder, _ = dof_set
    r = live.post("/api/reconstruct", files=mutate(_files(folder)))
    assert r.status_code == 422, r.text
    assert message in r.json()["detail"]


def test_bad_zip_and_wrong_type(live: TestClient) -> None:
    r = live.post("/api/reconstruct", content=b"PK\x03\x04garbage", headers={"content-type": "application/zip"})
    assert r.status_code == 422 and "zip" in r.json()["detail"]
    r = live.post("/api/reconstruct", content=b"hello", headers={"content-type": "text/plain"})
    assert r.status_code == 415 and r.json()["detail"]


def test_upload_over_the_limit_is_413(tmp_path: Path, sim_calibration_file: Path,
                                      dof_set: tuple[Path, np.ndarray]) -> None:
    folder, _ = dof_set
    settings = live_settings(tmp_path, sim_calibration_file, max_upload_mb=0.05, autostart=False)
    with TestClient(create_app(settings)) as client:
        r = client.post("/api/reconstruct", files=_files(folder))
        assert r.status_code == 413 and "limit" in r.json()["detail"]
        r = client.post("/api/reconstruct", content=_zip(folder), headers={"content-type": "application/zip"})
        assert r.status_code == 413
