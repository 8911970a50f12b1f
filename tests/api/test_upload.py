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


def test_multipart_upload_reconstructs_the_dof_target(
    live: TestClient, dof_set: tuple[Path, np.ndarray]
) -> None:
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


def test_upload_gives_sigma_and_its_two_parts(live: TestClient,
                                              dof_set: tuple[Path, np.ndarray]) -> None:
    """σ is the total, noise ⊕ calibration: both parts as maps and as medians in the summary."""
    folder, _ = dof_set
    maps = {}
    for field in ("sigma", "sigma_noise", "sigma_model"):
        r = live.post(f"/api/reconstruct?format=npy&field={field}", files=_files(folder))
        assert r.status_code == 200, r.text
        maps[field] = np.load(io.BytesIO(r.content)).astype(np.float64)
    ok = np.isfinite(maps["sigma"])
    assert ok.mean() > 0.3 and np.array_equal(ok, np.isfinite(maps["sigma_model"]))
    parts = maps["sigma_noise"][ok] ** 2 + maps["sigma_model"][ok] ** 2
    np.testing.assert_allclose(maps["sigma"][ok] ** 2, parts, rtol=1e-4)
    assert np.median(maps["sigma_model"][ok]) > 0.0  # the simulator's calibration has a jackknife
    body = live.post("/api/reconstruct", files=_files(folder)).json()
    assert body["sigma_median_mm"] == pytest.approx(float(np.median(maps["sigma"][ok])), rel=1e-6)
    model_median = float(np.median(maps["sigma_model"][ok]))
    assert body["sigma_model_median_mm"] == pytest.approx(model_median, rel=1e-6)


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
    r = live.post(
        "/api/reconstruct",
        content=b"PK\x03\x04garbage",
        headers={"content-type": "application/zip"},
    )
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
        r = client.post(
            "/api/reconstruct", content=_zip(folder), headers={"content-type": "application/zip"}
        )
        assert r.status_code == 413


def _rms_ratio(depth: np.ndarray, sigma: np.ndarray, truth: np.ndarray) -> float:
    ok = np.isfinite(depth) & np.isfinite(sigma) & np.isfinite(truth)
    assert ok.mean() > 0.3
    return float(np.sqrt(np.mean(((depth[ok] - truth[ok]) / sigma[ok]) ** 2)))


def test_sigma_is_honest_and_the_same_from_python_rest_and_cli(
    live: TestClient, sim_calibration_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A twin camera 4× noisier than the nominal sensor: every path fits the noise to the set."""
    from app.calib import load_calibration
    from app.cli import main
    from app.devices.sim import SimulatedWorld, render_capture_set
    from app.devices.sim.radiometry import SensorModel
    from app.recon import Reconstructor, SensorNoise

    nominal = SensorModel()  # 16× fewer electrons for the same DN: shot and read σ 4× the nominal
    noisy = SensorModel(
        full_well_e=nominal.full_well_e / 16, photons_scale=nominal.photons_scale / 16
    )
    world = SimulatedWorld("dof_target", seed=7, sensor=noisy)
    capture, truth, _ = render_capture_set("dof_target", seed=7, world=world)
    folder = write_capture_set(tmp_path / "set", capture)
    truth = np.asarray(truth)

    cal = load_calibration(sim_calibration_file)
    py = Reconstructor(cal).run(capture.frames, max_code=capture.max_code)
    assert py.noise_source == "set" and py.noise is not None
    ratio_py = _rms_ratio(py.depth, py.sigma, truth)

    r = live.post("/api/reconstruct", files=_files(folder))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["noise_source"] == "set"
    assert body["read_noise_dn"] == pytest.approx(py.noise.read_noise_dn)
    # the twin's projector is sinusoidal: no table on any path, and each says so alike
    assert body["phase_error_source"] == py.phase_error_source == "none"
    rest_depth = np.load(
        io.BytesIO(live.post("/api/reconstruct?format=npy", files=_files(folder)).content)
    )
    r = live.post("/api/reconstruct?format=npy&field=sigma", files=_files(folder))
    assert r.status_code == 200 and "sigma.npy" in r.headers["content-disposition"]
    rest_sigma = np.load(io.BytesIO(r.content))
    ratio_rest = _rms_ratio(rest_depth, rest_sigma, truth)

    assert (
        main(
            [
                "reconstruct",
                str(folder),
                "-c",
                str(sim_calibration_file),
                "-o",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    cli_line = capsys.readouterr().out
    assert "noise_source=set" in cli_line and "phase_error=none" in cli_line
    cli_depth, cli_sigma = (
        np.load(tmp_path / "out" / "depth.npy"),
        np.load(tmp_path / "out" / "sigma.npy"),
    )
    ratio_cli = _rms_ratio(cli_depth, cli_sigma, truth)

    print(f"RMS(error/sigma): python {ratio_py:.3f}, REST {ratio_rest:.3f}, CLI {ratio_cli:.3f}")
    for ratio in (ratio_py, ratio_rest, ratio_cli):
        assert 0.8 <= ratio <= 1.25
    # one noise estimate, one validity rule: the same pixels and the same σ on every path
    for depth, sigma in ((rest_depth, rest_sigma), (cli_depth, cli_sigma)):
        assert np.array_equal(np.isfinite(depth), py.valid)
        np.testing.assert_allclose(sigma[py.valid], py.sigma[py.valid], rtol=1e-5)
    # the nominal model would make σ about four times too small
    nom = Reconstructor(cal).run(capture.frames, max_code=capture.max_code,
                                 noise=SensorNoise.typical(capture.max_code))
    assert nom.noise_source == "given" and _rms_ratio(nom.depth, nom.sigma, truth) > 2.5
