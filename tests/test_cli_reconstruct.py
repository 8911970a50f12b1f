"""``fringescope reconstruct`` end to end on a synthetic capture set."""

from __future__ import annotations

import cv2
import numpy as np

from app.calib import save_calibration
from app.capture import CaptureSet, write_capture_set
from app.capture.ply import read_ply
from app.cli import main
from app.core.schedule import SCHEDULES, PatternSchedule
from app.devices.sim.analytic_rig import Rig, bump_surface
from tests.helpers.cli_sets import write_bump_set


def test_reconstruct_writes_outputs(tmp_path, capsys):
    h = write_bump_set(tmp_path)
    out = tmp_path / "out"
    rc = main(["reconstruct", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json"),
               "-o", str(out), "--range", "0,30"])
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and "valid" in lines[0] and "mm" in lines[0] and "ms" in lines[0]
    depth = np.load(out / "depth.npy")
    assert depth.dtype == np.float32 and depth.shape == h.shape
    assert np.isnan(depth[:8, :8]).all()
    ok = np.isfinite(depth)
    assert ok.mean() > 0.95
    assert np.max(np.abs(depth[ok] - h[ok])) < 0.1
    cloud = read_ply(out / "points.ply")
    assert cloud.size == ok.sum()
    sigma = np.load(out / "sigma.npy")
    assert sigma.dtype == np.float32 and np.array_equal(np.isfinite(sigma), ok)
    assert 0.0 < np.nanmedian(sigma) < 0.1
    np.testing.assert_array_equal(cloud["sigma_mm"], sigma[ok])
    for name in ("depth.png", "reason.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] >= h.shape[0]


def test_reconstruct_numpy_path_matches(tmp_path, capsys):
    write_bump_set(tmp_path)
    for flag, sub in (([], "a"), (["--numpy"], "b")):
        assert main(["reconstruct", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json"),
                     "-o", str(tmp_path / sub), *flag]) == 0
    a, b = np.load(tmp_path / "a" / "depth.npy"), np.load(tmp_path / "b" / "depth.npy")
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.nanmax(np.abs(a - b)) < 1e-3
    assert "(numpy)" in capsys.readouterr().out


def test_missing_folder_is_one_line_error(tmp_path, capsys):
    write_bump_set(tmp_path)
    rc = main(["reconstruct", str(tmp_path / "nope"), "-c", str(tmp_path / "calibration.json"),
               "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "nope" in err[0]
    assert not (tmp_path / "out").exists()


def test_bad_calibration_is_one_line_error(tmp_path, capsys):
    write_bump_set(tmp_path)
    (tmp_path / "calibration.json").write_text("{}")
    rc = main(["reconstruct", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json"),
               "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "calibration" in err[0]


def test_a_calibration_nested_too_deeply_is_one_line_error(tmp_path, capsys):
    write_bump_set(tmp_path)
    (tmp_path / "calibration.json").write_text("[" * 100_000 + "]" * 100_000)
    rc = main(["reconstruct", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json"),
               "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "nested 100000 levels deep" in err[0], err


def test_corrupted_geometric_calibration_is_one_line_error(tmp_path, capsys):
    import json

    write_bump_set(tmp_path)
    data = json.loads((tmp_path / "calibration.json").read_text())
    data["model"] = {"name": "geometric", "rvec": [0.0, "x", 0.0]}
    (tmp_path / "calibration.json").write_text(json.dumps(data))
    rc = main(["reconstruct", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json"),
               "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "model" in err[0], err



def test_reconstruct_applies_the_calibration_carry_over_rule(tmp_path, capsys):
    """A 9-frame set reconstructs with a calibration made with the paper's 16 frames (same finest
    pattern, same depth); a set whose finest pattern differs is refused with one line, exit 2."""
    h = write_bump_set(tmp_path)
    cal = str(tmp_path / "calibration.json")
    for name, schedule in (
        ("nine", SCHEDULES["geometric-9"]),
        ("finest12", PatternSchedule((1, 4, 12), 4)),
    ):
        rig = Rig(schedule=schedule)
        write_capture_set(
            tmp_path / name,
            CaptureSet(rig.render(h, noise=0.5, rng=np.random.default_rng(5)), schedule),
        )
    assert (
        main(["reconstruct", str(tmp_path / "nine"), "-c", cal, "-o", str(tmp_path / "out9")]) == 0
    )
    depth = np.load(tmp_path / "out9" / "depth.npy")
    ok = np.isfinite(depth)
    assert ok.mean() > 0.95 and np.max(np.abs(depth[ok] - h[ok])) < 0.1
    capsys.readouterr()
    rc = main(["reconstruct", str(tmp_path / "finest12"), "-c", cal, "-o", str(tmp_path / "out12")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "finest pattern" in err[0] and "finest12" in err[0]
    assert not (tmp_path / "out12").exists()


def test_explicit_min_modulation_replaces_the_validity_rule(tmp_path, capsys):
    write_bump_set(tmp_path)
    args = ["reconstruct", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json")]
    assert main([*args, "-o", str(tmp_path / "rule")]) == 0
    # B = 90: none pass
    assert main([*args, "-o", str(tmp_path / "high"), "--min-modulation", "200"]) == 0
    assert np.isfinite(np.load(tmp_path / "rule" / "depth.npy")).mean() > 0.95
    assert np.isnan(np.load(tmp_path / "high" / "depth.npy")).all()
    capsys.readouterr()
    rc = main([*args, "-o", str(tmp_path / "bad"), "--min-modulation", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "min_modulation" in err[0]
    assert not (tmp_path / "bad").exists()


def _bracket(tmp_path):
    """Two sets of one scene, left half white and right half 1/50 as bright, at 10 and 40 ms:
    neither alone measures the whole scene."""
    rig = Rig()
    h = bump_surface(rig)
    albedo = np.where(np.arange(rig.width) < rig.width // 2, 1.0, 0.02)[None, :] * np.ones(
        (rig.height, 1)
    )
    for exposure_ms, seed in ((10.0, 1), (40.0, 2)):
        gain = exposure_ms / 10.0
        frames = rig.render(
            h,
            background=110.0 * gain * albedo,
            amplitude=90.0 * gain * albedo,
            noise=0.6,
            rng=np.random.default_rng(seed),
        )
        write_capture_set(
            tmp_path / f"set{exposure_ms:g}",
            CaptureSet(frames, rig.schedule, exposure_ms=exposure_ms),
        )
    save_calibration(rig.calibration(), tmp_path / "calibration.json")
    return h


def test_an_exposure_bracket_is_fused(tmp_path, capsys):
    h = _bracket(tmp_path)
    cal = str(tmp_path / "calibration.json")
    for sets, sub in (([tmp_path / "set10"], "short"), ([tmp_path / "set40"], "long"),
                      ([tmp_path / "set10", tmp_path / "set40"], "both")):
        assert main(["reconstruct", *map(str, sets), "-c", cal, "-o", str(tmp_path / sub)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and "fused from 10 ms" in lines[2] and "40 ms" in lines[2]
    valid = {
        sub: np.isfinite(np.load(tmp_path / sub / "depth.npy")) for sub in ("short", "long", "both")
    }
    assert valid["short"].mean() < 0.6 and valid["long"].mean() < 0.6
    assert valid["both"].mean() > 0.99
    depth = np.load(tmp_path / "both" / "depth.npy")
    assert np.nanmax(np.abs(depth - h)) < 0.5
    sigma = np.load(tmp_path / "both" / "sigma.npy")
    assert np.array_equal(np.isfinite(sigma), valid["both"])
    assert read_ply(tmp_path / "both" / "points.ply").size == valid["both"].sum()


def test_a_bracket_of_different_schedules_is_one_line_error(tmp_path, capsys):
    _bracket(tmp_path)
    rig = Rig()
    nine = SCHEDULES["geometric-9"]
    frames = np.zeros((nine.n_frames, rig.height, rig.width), np.uint8)
    write_capture_set(tmp_path / "nine", CaptureSet(frames, nine))
    rc = main(
        [
            "reconstruct",
            str(tmp_path / "set10"),
            str(tmp_path / "nine"),
            "-c",
            str(tmp_path / "calibration.json"),
            "-o",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "nine" in err[0] and "schedule" in err[0], err
    assert not (tmp_path / "out").exists()
