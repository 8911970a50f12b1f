"""``calibrate_folder`` and ``fringescope calibrate`` on rendered fringe sets of the analytic
rig."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from app.calib import BoardSpec, calibrate_sets, height_mm, load_calibration
from app.capture.captureset import CaptureSet, write_capture_set
from app.cli import main
from tests.helpers.calib_rig import (
    STANDARD_POSES,
    Rig,
    board_pose,
    fringe_frames,
    fringe_stack,
    raycast_scene,
    render_board,
)

BOARD = BoardSpec("checkerboard", 9, 6, 3.0)


def _fringe_set(rig: Rig, rmat, tvec, seed: int) -> CaptureSet:
    """16 uint8 frames: board albedo × (110 + 100 cos(k/k_max · φ + δ)) + noise."""
    albedo = render_board(BOARD, rmat, tvec, rig).astype(np.float64) / 240.0
    phi = rig.plane_phase_map(rmat[:, 2], tvec).astype(np.float64)
    return CaptureSet(fringe_stack(rig, phi, albedo, noise_dn=0.5, seed=seed), rig.schedule)


@pytest.fixture(scope="module")
def calib_dir(tmp_path_factory):
    rig = Rig()
    d = tmp_path_factory.mktemp("calib")
    (d / "board.json").write_text(json.dumps(BOARD.to_dict()))
    truth = []
    for i, (depth, ax, ay, az, sh) in enumerate(STANDARD_POSES):
        r, t = board_pose(BOARD, depth, ax, ay, az, sh)
        truth.append((r, t))
        write_capture_set(d / f"pose_{i:02d}", _fringe_set(rig, r, t, i))
    return d, rig, truth


@pytest.fixture(scope="module")
def cli_calibration(calib_dir, tmp_path_factory) -> tuple[int, str, Path]:  # noqa: ANN001
    """``fringescope calibrate <calib_dir> -o cal.json`` run once for the module (a full
    calibration, ~20 s of CPU): its exit code, what it printed and the file it wrote. Read by
    the test of the command's output and by the validate test, which needs a calibration."""
    d, _, _ = calib_dir
    out = tmp_path_factory.mktemp("cli_cal") / "cal.json"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["calibrate", str(d), "-o", str(out)])
    return code, printed.getvalue(), out


def test_cli_calibrate_writes_file_and_table(calib_dir, cli_calibration):
    d, rig, truth = calib_dir
    code, text, out = cli_calibration
    assert code == 0
    assert "pose_05" in text and "reproj_px" in text and "fit_rms_mm" in text and "wrote" in text
    assert (
        "held-out rms_mm" in text
        and "\neq5 " in text
        and "\ngeometric " in text
        and "<- active" in text
    )
    cal = load_calibration(out)
    assert set(cal.held_out) == {"eq5", "geometric"}
    eq5, geo = cal.held_out["eq5"]["rms_mm"], cal.held_out["geometric"]["rms_mm"]
    best = "eq5" if eq5 < 0.98 * geo else "geometric"
    assert cal.model.name == best and f"active model: {best}" in text
    # the coverage of the image x height cells, per bin a map, and the pose to add in words
    assert "coverage: " in text and "% of the image x 0-20 mm cells calibrated" in text
    assert text.count("  heights ") == 4 and "max sigma_model" in text
    assert "next pose" in text and "deg about the vertical axis" in text
    assert len(cal.pose_residuals) == len(STANDARD_POSES)
    assert all(p["corners"] == BOARD.n_points for p in cal.pose_residuals)
    # Heights of a fresh plane 10 mm above the reference, from its exact phase.
    r0, t0 = truth[0]
    n = r0[:, 2] if r0[:, 2] @ t0 < 0 else -r0[:, 2]
    point = t0 + 10.0 * n
    phase = rig.plane_phase_map(n, point)
    vv, uu = np.mgrid[150:330, 220:420]
    z = height_mm(cal, uu, vv, phase[150:330, 220:420])
    assert abs(np.mean(z) - 10.0) < 0.05 and np.abs(z - 10.0).max() < 0.2


@pytest.mark.parametrize("model", ["eq5", "geometric"])
def test_cli_calibrate_forced_model(calib_dir, tmp_path, capsys, model):
    d, rig, truth = calib_dir
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(d), "-o", str(out), "--model", model]) == 0
    assert f"active model: {model}" in capsys.readouterr().out
    cal = load_calibration(out)
    assert cal.model.name == model
    r0, t0 = truth[0]
    n = r0[:, 2] if r0[:, 2] @ t0 < 0 else -r0[:, 2]
    phase = rig.plane_phase_map(n, t0 + 10.0 * n)
    vv, uu = np.mgrid[150:330, 220:420]
    z = height_mm(cal, uu, vv, phase[150:330, 220:420])
    assert abs(np.mean(z) - 10.0) < 0.05 and np.abs(z - 10.0).max() < 0.2


def test_boards_covering_too_little_name_the_missing_region():
    from app.calib.fitting import _check_coverage
    from app.core.depth_model import BoardSamples

    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 300, 500), rng.uniform(0, 200, 500)  # top left of a 640 x 480 image
    s = BoardSamples(
        u,
        v,
        np.zeros((500, 2)),
        np.ones(500),
        np.ones(500),
        np.zeros(500, np.int64),
        (640, 480),
        36,
        608,
    )
    with pytest.raises(ValueError, match=r"no control point in the .*bottom right.*ninths"):
        _check_coverage(s)
    u2 = np.r_[u, rng.uniform(0, 639, 500)]
    v2 = np.r_[v, rng.uniform(0, 479, 500)]
    s2 = BoardSamples(
        u2,
        v2,
        np.zeros((1000, 2)),
        np.ones(1000),
        np.ones(1000),
        np.zeros(1000, np.int64),
        (640, 480),
        36,
        608,
    )
    assert _check_coverage(s2) == []


def test_calibrate_sets_errors_name_the_pose(calib_dir):
    d, rig, truth = calib_dir
    from app.capture.captureset import read_capture_set

    sets = [read_capture_set(d / f"pose_{i:02d}") for i in range(4)]
    blank = CaptureSet(np.full_like(sets[2].frames, 100), sets[2].schedule)
    with pytest.raises(ValueError, match=r"^pose 2 \(pose_02\): board not found"):
        calibrate_sets(BOARD, [sets[0], sets[1], blank, sets[3]])
    rep = calibrate_sets(BOARD, [sets[0], sets[1], blank, sets[3]], robust=True)
    assert rep.poses[2].dropped and rep.poses[2].corners == 0
    assert math.isfinite(rep.rms_mm)
    with pytest.raises(ValueError, match="^poses: need at least 3"):
        calibrate_sets(BOARD, sets[:2])


def test_cli_calibrate_bad_folder_is_one_line(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path / "nope"), "-o", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err
    assert "calibration folder not found" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "c").mkdir()
    assert main(["calibrate", str(tmp_path / "c"), "-o", str(tmp_path / "c.json")]) == 2
    assert "board.json" in capsys.readouterr().err


def _reference(truth):
    r0, t0 = truth[0]
    n = r0[:, 2] if r0[:, 2] @ t0 < 0 else -r0[:, 2]
    return n, t0


def _write_scene(path, rig, pts, albedo, seed=11):
    write_capture_set(path, CaptureSet(fringe_frames(rig, pts, albedo, seed=seed), rig.schedule))


def test_cli_validate_plane_sphere_feature(calib_dir, cli_calibration, tmp_path, capsys):
    d, rig, truth = calib_dir
    code, _, cal_path = cli_calibration  # the module's `calibrate` run (read only)
    assert code == 0
    n, t0 = _reference(truth)
    # A plane 10 mm up, tilted 30° about the camera's y axis.
    tilt = np.array([[np.cos(0.52), 0, np.sin(0.52)], [0, 1, 0], [-np.sin(0.52), 0, np.cos(0.52)]])
    normal = tilt @ n
    pts, _ = raycast_scene(rig, (normal, t0 + 10.0 * n))
    _write_scene(tmp_path / "plane", rig, pts, np.full(pts.shape[:2], 0.8))
    out = tmp_path / "plane.json"
    roi = "200,150,440,330"
    assert main(["validate", str(tmp_path / "plane"), "-c", str(cal_path), "--plane", "--roi", roi,
                 "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "accuracy_mm" in text and "precision_mm" in text and "flatness_mm" in text
    fig = json.loads(out.read_text())
    assert fig["valid_fraction"] > 0.99 and fig["roi"] == [200, 150, 440, 330]
    assert fig["accuracy_mm"] < 0.02 and fig["precision_mm"] < 0.05 and fig["flatness_mm"] < 0.5
    assert len(fig["bins"]) > 10
    # A sphere of 8 mm diameter resting on the reference plane.
    centre = t0 + 4.0 * n
    pts, sid = raycast_scene(rig, (n, t0), sphere=(centre, 4.0))
    _write_scene(tmp_path / "sphere", rig, pts, np.where(sid == 1, 0.6, 0.9))
    out = tmp_path / "sphere.json"
    assert main(["validate", str(tmp_path / "sphere"), "-c", str(cal_path), "--sphere", "8",
                 "--json", str(out)]) == 0
    fig = json.loads(out.read_text())
    assert abs(fig["ps_mm"]) < 0.05 and fig["diameter_mm"] == pytest.approx(8.0 + fig["ps_mm"])
    assert fig["pf_mm"] < 0.5
    # A dark thread (0.8 mm) lying on a plane 8 mm up.
    base = t0 + 8.0 * n
    axis = np.cross(n, [0.0, 0.0, 1.0]) + np.cross(n, [1.0, 0.0, 0.0]) * 0.3
    axis /= np.linalg.norm(axis)
    pts, sid = raycast_scene(rig, (n, base), cylinder=(base + 0.4 * n, axis, 0.4))
    _write_scene(tmp_path / "thread", rig, pts, np.where(sid == 2, 0.35, 0.9))
    out = tmp_path / "thread.json"
    assert (
        main(
            [
                "validate",
                str(tmp_path / "thread"),
                "-c",
                str(cal_path),
                "--feature",
                "--polarity",
                "dark",
                "--roi",
                "200,140,440,340",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    fig = json.loads(out.read_text())
    assert (
        fig["height_mm"] == pytest.approx(0.8, abs=0.01) and fig["count"] > 50
    )  # the suture target
    assert fig["height_std_mm"] < 0.1
    # Bad input: one line, exit 2.
    assert (
        main(
            ["validate", str(tmp_path / "plane"), "-c", str(cal_path), "--plane", "--roi", "1,2,3"]
        )
        == 2
    )
    assert "roi" in capsys.readouterr().err


def test_a_board_on_the_central_half_is_accepted_and_its_gaps_named():
    """A bench board that reaches only the central half of the field calibrates; the ninths it
    misses are returned (the supported region leaves them out), not refused."""
    from app.calib.fitting import _check_coverage
    from app.core.depth_model import BoardSamples

    rng = np.random.default_rng(1)
    u, v = rng.uniform(160, 480, 800), rng.uniform(120, 360, 800)  # central half of 640 x 480
    s = BoardSamples(
        u,
        v,
        np.zeros((800, 2)),
        np.ones(800),
        np.ones(800),
        np.zeros(800, np.int64),
        (640, 480),
        36,
        608,
    )
    missing = _check_coverage(s)
    assert "centre" not in missing and set(missing) <= {
        "top left",
        "top right",
        "bottom left",
        "bottom right",
        "top centre",
        "bottom centre",
        "middle left",
        "middle right",
    }
    small = BoardSamples(
        u[:50] * 0.2 + 256,
        v[:50] * 0.2 + 192,
        np.zeros((50, 2)),
        np.ones(50),
        np.ones(50),
        np.zeros(50, np.int64),
        (640, 480),
        36,
        608,
    )  # a patch of 64 x 48 px at the centre
    with pytest.raises(ValueError, match="cover too little"):
        _check_coverage(small)
