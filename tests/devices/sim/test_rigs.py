"""Rig presets of the twin: the endoscope rig's sensor, lens distortion, 12-bit frames, partial
boards."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from app.calib import calibrate_folder
from app.calib.board import detect_board, texture_to_u8
from app.capture.captureset import read_capture_set
from app.cli import main
from app.core.board import BoardSpec
from app.devices.sim import (
    RIG_NAMES,
    SimulatedWorld,
    default_rig,
    render_capture_set,
    rig_by_name,
    simulate_calibration_folder,
)
from app.devices.sim.offline import central_fraction, partial_board_spec
from app.devices.sim.scenes import board_points_mm, board_poses, sim_board
from app.devices.sim.scenes.base import frame_from_normal


def _triangulation_deg(rig) -> float:
    """Angle between the camera ray and the projector ray at the reference point."""
    p = rig.reference_point_mm
    a, b = (
        p / np.linalg.norm(p),
        (p - rig.projector.centre) / np.linalg.norm(p - rig.projector.centre),
    )
    return math.degrees(math.acos(float(a @ b)))


def test_presets_by_name_differ_where_the_issue_asks():
    assert set(RIG_NAMES) == {"default", "endoscope"}
    d, e = rig_by_name("default"), rig_by_name("endoscope")
    assert np.array_equal(d.K, default_rig().K) and np.array_equal(d.dist, default_rig().dist)
    assert e.image_size != d.image_size and e.K[0, 0] != d.K[0, 0]
    assert e.dist[0] == pytest.approx(-0.25) and e.bit_depth == 12 and d.bit_depth == 8
    assert _triangulation_deg(e) > 1.5 * _triangulation_deg(d)
    assert e.partial_boards and not d.partial_boards
    assert not np.any(rig_by_name("endoscope", distortion=False).dist)
    with pytest.raises(ValueError, match="rig"):
        rig_by_name("fisheye")


def test_endoscope_distortion_is_monotonic_to_the_corners():
    """Barrel distortion must stay invertible over the whole image (else rays fold over)."""
    cam = rig_by_name("endoscope").camera
    w, h = cam.image_size
    r_d = (
        math.hypot(max(cam.K[0, 2], w - 1 - cam.K[0, 2]), max(cam.K[1, 2], h - 1 - cam.K[1, 2]))
        / cam.K[0, 0]
    )
    k1 = cam.dist[0]
    r_fold = math.sqrt(-1 / (3 * k1))  # d/dr [r (1 + k1 r²)] = 0
    assert r_d < 0.95 * r_fold * (1 + k1 * r_fold**2)


@pytest.fixture(scope="module")
def endo_plane() -> SimulatedWorld:
    w = SimulatedWorld("plane", seed=4, rig="endoscope")
    _ = w.renderer
    return w


def test_rendered_straight_line_is_the_curve_cv2_projects(endo_plane):
    """A straight 3-D line on the rendered plane (s = const in its frame) images as the curve
    cv2.projectPoints gives for the rig's K and distortion — and that curve is far from straight."""
    rig = endo_plane.rig
    hf = endo_plane.scene.surface
    _, points = endo_plane.truth(0.0)
    # (H, W) in-plane coordinate of each pixel's hit
    s = hf.local(points.astype(np.float64))[..., 0]
    s_line = 15.0  # off centre: radial lines stay straight under radial distortion
    rows, cols = [], []
    for v in range(40, rig.image_size[1] - 40, 16):
        row = s[v]
        k = np.flatnonzero((row[:-1] - s_line) * (row[1:] - s_line) <= 0)
        assert len(k) == 1
        k = int(k[0])
        rows.append(v)
        cols.append(k + (s_line - row[k]) / (row[k + 1] - row[k]))
    rows_a, cols_a = np.array(rows, float), np.array(cols)
    # the 3-D line: points of the plane with s = s_line, projected by OpenCV
    t = np.linspace(-40, 40, 4001)
    line = hf.origin + s_line * hf.axes[:, 0] + t[:, None] * hf.axes[:, 1]
    uv, _ = cv2.projectPoints(line, np.zeros(3), np.zeros(3), rig.K, rig.dist)
    r_norm = np.hypot(line[:, 0] / line[:, 2], line[:, 1] / line[:, 2])
    uv = uv.reshape(-1, 2)[r_norm < 1.0]  # short of the radius where r(1 + k1 r²) folds back
    order = np.argsort(uv[:, 1])
    u_cv = np.interp(rows_a, uv[order, 1], uv[order, 0])
    assert np.max(np.abs(cols_a - u_cv)) < 1e-3  # px: the renderer's rays are OpenCV's model
    # and it is a curve: far from the chord through its ends
    chord = cols_a[0] + (cols_a[-1] - cols_a[0]) * (rows_a - rows_a[0]) / (rows_a[-1] - rows_a[0])
    assert np.max(np.abs(cols_a - chord)) > 20.0


def test_endoscope_frames_are_12_bit(endo_plane):
    cs, depth, _ = render_capture_set("plane", world=endo_plane, seed=4, exposure_ms=30.0)
    assert cs.frames.dtype == np.uint16 and cs.frames.shape == (16, 1024, 1280)
    assert 1000 < int(cs.frames.max()) <= 4095
    assert cs.bit_depth == 12 and cs.extra["simulated"]["rig"] == "endoscope"
    assert np.isfinite(depth).mean() > 0.99


def test_default_rig_capture_meta_unchanged(plane_world):
    cs, _, _ = render_capture_set("plane", world=plane_world, seed=1)
    assert (
        cs.frames.dtype == np.uint8
        and "bit_depth" not in cs.extra
        and "rig" not in cs.extra["simulated"]
    )


@pytest.mark.parametrize("name", RIG_NAMES)
def test_partial_board_spec_keeps_the_grid_in_the_central_half(name):
    rig = rig_by_name(name)
    poses = board_poses(rig, 8, seed=3)
    full = sim_board("checkerboard")
    spec = partial_board_spec(rig, full, poses)
    assert spec.pitch_mm < full.pitch_mm and (spec.cols, spec.rows) == (full.cols, full.rows)
    assert 0.45 < central_fraction(rig, spec.pitch_mm, spec, poses) <= 0.5
    with pytest.raises(ValueError, match="fraction"):
        partial_board_spec(rig, full, poses, fraction=2.0)


def test_cli_rig_option(tmp_path, capsys):
    assert main(["simulate", "plane", "-o", str(tmp_path), "--rig", "fisheye"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--rig" in err


@pytest.fixture(scope="module")
def endo_calibration(tmp_path_factory):
    return simulate_calibration_folder(
        tmp_path_factory.mktemp("endo") / "cal", poses=6, seed=2, rig="endoscope"
    )


@pytest.mark.slow
def test_partial_boards_detected_in_the_central_half(endo_calibration):
    """Every pose's detected corners lie in the central half of the image and sit where
    cv2.projectPoints puts the true board corners through the distorted lens."""
    rig = rig_by_name("endoscope")
    spec_json = json.loads((endo_calibration / "board.json").read_text())
    spec = BoardSpec.from_dict(spec_json)
    cal_board = spec
    w, h = rig.image_size
    for k in range(6):
        cs = read_capture_set(endo_calibration / f"pose_{k:02d}")
        assert cs.frames.dtype == np.uint16 and cs.frames.max() <= 4095
        mean = cs.frames.astype(np.float32).mean(0)
        det = detect_board(texture_to_u8(mean), cal_board)
        assert det.found
        uv = det.image_points.reshape(-1, 2)
        assert np.all(np.abs(uv[:, 0] - (w - 1) / 2) <= w / 4) and np.all(
            np.abs(uv[:, 1] - (h - 1) / 2) <= h / 4
        )
        sim = cs.extra["simulated"]
        assert sim["partial_board"] is True
        truth = rig.camera.project(np.array(sim["board_origin_mm"]) + board_points_mm(spec)
                                   @ np.array(sim["board_axes"]).T)
        # detection order is free
        nearest = np.linalg.norm(uv[:, None] - truth[None], axis=2).min(axis=1)
        assert np.max(nearest) < 0.3


@pytest.mark.slow
def test_endoscope_rig_calibrates_end_to_end(endo_calibration):
    """The existing Eq. (5) calibration recovers the endoscope's lens from partial boards."""
    rep = calibrate_folder(endo_calibration)
    cal = rep.calibration
    rig = rig_by_name("endoscope")
    assert cal.image_size == rig.image_size
    assert np.allclose(
        cal.camera_matrix[[0, 1, 0, 1], [0, 1, 2, 2]], rig.K[[0, 1, 0, 1], [0, 1, 2, 2]], atol=3.0
    )
    assert cal.dist_coeffs[0] == pytest.approx(-0.25, abs=0.02)
    assert rep.reprojection_px < 0.15
    assert rep.rms_mm < 0.05
    lo, hi = cal.height_range_mm
    assert lo < 0.5 and hi > 15.0
    # the reference plane is the rig's (pose 0)
    origin, axes = frame_from_normal(rig.reference_point_mm, rig.reference.normal)
    assert float(np.degrees(np.arccos(abs(cal.plane_normal @ axes[:, 2])))) < 0.2


def test_rig_selected_by_settings_everywhere_the_simulator_is_built(tmp_path):
    """FRINGESCOPE_SIM_RIG reaches the devices of the factory and of the service, and the
    simulator's own calibration file is per rig (nothing is rendered here)."""
    from app.config import Settings
    from app.devices.factory import create_devices as factory_devices
    from app.service.calibration_store import sim_file_name
    from app.service.devices import create_devices as service_devices
    from app.service.devices import device_specs

    settings = Settings(data_dir=tmp_path, sim_rig="endoscope", bit_depth=12, viewer=False)
    for devs in (factory_devices(device_specs(settings)), service_devices(settings)):
        cam = devs.camera
        assert cam.world.rig.name == "endoscope"
        caps = cam.capabilities
        assert (caps.width, caps.height) == (1280, 1024) and 12 in caps.bit_depths
    assert sim_file_name(settings) == "sim-endoscope.json"
    assert sim_file_name(Settings(data_dir=tmp_path)) == "sim.json"
    with pytest.raises(ValueError):
        Settings(sim_rig="fisheye")


def test_calibration_reads_the_capture_bit_depth():
    from app.calib.fitting import capture_max_code
    from app.capture.captureset import CaptureSet
    from app.recon.patterns import PatternSchedule

    frames = np.zeros((16, 4, 4), np.uint16)
    sched = PatternSchedule()
    assert (
        capture_max_code(CaptureSet(frames=frames, schedule=sched, extra={"bit_depth": 12})) == 4095
    )
    assert capture_max_code(CaptureSet(frames=frames, schedule=sched)) is None
    with pytest.raises(ValueError, match="bit_depth"):
        capture_max_code(CaptureSet(frames=frames, schedule=sched, extra={"bit_depth": 20}))
