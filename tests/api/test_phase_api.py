"""POST /api/phase (calibration-free decoding of an upload) and the status's bit depth and
schedule."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.capture import CaptureSet, write_capture_set
from app.config import Settings
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.main import create_app
from app.recon import PatternSchedule

HET = PatternSchedule(frequencies=(608 / 48, 608 / 45, 608 / 42), steps=4, unwrap="heterodyne")


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    data = tmp_path_factory.mktemp("phase-api")
    # no controller: the devices are not all simulated, so no simulator calibration is made in
    # the background (shutting down waited for it, up to 120 s) and none is ever active
    settings = Settings(data_dir=data, viewer=False, autostart=False, controller="none")
    with TestClient(create_app(settings)) as c:
        assert c.get("/api/status").json()["calibration"] is None
        yield c


def _set(folder: Path) -> tuple[Rig, np.ndarray]:
    rig = Rig(schedule=HET)
    h = bump_surface(rig)
    frames = rig.render(
        h,
        background=2000,
        amplitude=1000,
        noise=3.0,
        dtype=np.uint16,
        max_code=4095,
        rng=np.random.default_rng(3),
    )
    frames[0:2, 40:50, 40:50] = 4095  # two shifts of four clipped: saturated
    frames[4, 60:70, 60:70] = 4095  # one clipped: recovered
    write_capture_set(folder, CaptureSet(frames, HET, bit_depth=12))
    return rig, h


def _files(folder: Path) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [
        (
            "files",
            (p.name, p.read_bytes(), "application/json" if p.suffix == ".json" else "image/png"),
        )
        for p in sorted(folder.iterdir())
    ]


def test_phase_of_an_uploaded_heterodyne_12_bit_set(client: TestClient, tmp_path: Path) -> None:
    rig, h = _set(tmp_path / "set")
    r = client.post("/api/phase", files=_files(tmp_path / "set"))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["bit_depth"] == 12 and body["schedule"]["unwrap"] == "heterodyne"
    assert body["recovered_pixels"] == 100 and 0.95 < body["valid_fraction"] < 1.0
    r = client.post("/api/phase?format=npy", files=_files(tmp_path / "set"))
    phase = np.load(io.BytesIO(r.content))
    assert np.isnan(phase[40:50, 40:50]).all()
    ok = np.isfinite(phase)
    assert np.max(np.abs(phase[ok] - rig.finest_phase(h)[ok])) < 0.05


@pytest.mark.parametrize(("edit", "key"), [
    (lambda m: m.update(bit_depth=10), "bit_depth"),
    (lambda m: m.update(channel="ultraviolet"), "channel"),
    (lambda m: m["pattern"].update(frequencies=[608 / 48, 608 / 42], steps=6), "frequencies"),
])
def test_bad_uploads_are_422_naming_the_key(client: TestClient, tmp_path: Path, edit, key) -> None:  # type: ignore[no-untyped-def]
    _set(tmp_path / "set")
    meta_path = tmp_path / "set" / "capture.json"
    meta = json.loads(meta_path.read_text())
    edit(meta)
    meta_path.write_text(json.dumps(meta))
    r = client.post("/api/phase", files=_files(tmp_path / "set"))
    assert r.status_code == 422 and key in r.text


def test_status_reports_bit_depth_and_schedule(client: TestClient) -> None:
    st = client.get("/api/status").json()
    assert st["bit_depth"] == 8
    assert st["schedule"]["frequencies"] == [1, 4, 12, 36] and st["schedule"]["steps"] == 4
