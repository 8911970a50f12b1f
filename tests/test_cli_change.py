"""``fringescope change`` end to end on synthetic capture sets of the analytic rig."""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest

from app.calib import save_calibration
from app.capture import CaptureSet, write_capture_set
from app.cli import main
from app.devices.sim.analytic_rig import Rig, bump_surface

BUMP_MM = 0.6


def _write(tmp_path, rig: Rig, name: str, height: np.ndarray, seed: int) -> str:
    frames = rig.render(height, noise=0.5, rng=np.random.default_rng(seed))
    write_capture_set(tmp_path / name, CaptureSet(frames, rig.schedule))
    return str(tmp_path / name)


@pytest.fixture
def sets(tmp_path):
    rig = Rig()
    h = bump_surface(rig)
    vv, uu = np.mgrid[0:rig.height, 0:rig.width]
    r = np.hypot(vv - 40, uu - 50) / 12.0  # a raised-cosine bump 24 px across
    bump = np.where(r < 1, 0.5 * BUMP_MM * (1 + np.cos(math.pi * np.minimum(r, 1))), 0.0)
    save_calibration(rig.calibration(), tmp_path / "calibration.json")
    ref = _write(tmp_path, rig, "ref", h, 1)
    cur = _write(tmp_path, rig, "cur", h + bump, 2)
    same = _write(tmp_path, rig, "same", h, 3)
    return tmp_path, ref, cur, same, bump


def test_change_writes_the_maps_and_one_summary_line(sets, capsys):
    tmp_path, ref, cur, _, bump = sets
    out = tmp_path / "out"
    assert main(["change", ref, cur, "-c", str(tmp_path / "calibration.json"),
                 "-o", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    line = lines[0]
    assert "changed" in line and "mm²" in line and "registration none (fixed scope)" in line
    rise = re.search(r"max rise \+([0-9.]+) ± ([0-9.]+) mm", line)
    assert rise is not None
    assert abs(float(rise.group(1)) - BUMP_MM) < 4 * float(rise.group(2)) + 0.05
    delta = np.load(out / "delta.npy")
    sigma = np.load(out / "sigma.npy")
    sig = np.load(out / "significance.npy")
    changed = np.load(out / "changed.npy")
    assert delta.dtype == sigma.dtype == sig.dtype == np.float32 and changed.dtype == bool
    assert delta.shape == bump.shape
    np.testing.assert_allclose(sig, np.abs(delta) / sigma, rtol=1e-5)
    assert changed[bump > BUMP_MM / 2].mean() >= 0.9
    assert changed[bump == 0].mean() < 0.01
    ok = np.isfinite(delta)
    assert np.sqrt(np.mean((delta - bump)[ok & (bump == 0)] ** 2)) < 0.05
    png = cv2.imread(str(out / "delta.png"))
    assert png is not None and png.shape[0] >= bump.shape[0] and png.shape[1] > bump.shape[1]
    assert not list(out.glob("*.tmp*"))


def test_an_unchanged_scene_reports_no_change(sets, capsys):
    tmp_path, ref, _, same, _ = sets
    assert main(["change", ref, same, "-c", str(tmp_path / "calibration.json"),
                 "-o", str(tmp_path / "o2")]) == 0
    line = capsys.readouterr().out.strip()
    assert "max rise none" in line and "max sink none" in line and "changed 0.00 mm²" in line
    assert not np.load(tmp_path / "o2" / "changed.npy").any()


def test_sets_of_another_image_size_are_one_line_exit_2(sets, capsys):
    tmp_path, ref, _, _, _ = sets
    small = Rig(width=100, height=80)
    other = _write(tmp_path, small, "small", bump_surface(small), 4)
    assert main(["change", ref, other, "-c", str(tmp_path / "calibration.json"),
                 "-o", str(tmp_path / "o3")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not comparable" in err and "100x80" in err
    assert not (tmp_path / "o3").exists()


def test_no_valid_overlap_is_one_line_exit_2(sets, capsys):
    tmp_path, ref, _, _, _ = sets
    rig = Rig()
    dark = np.full((rig.schedule.n_frames, rig.height, rig.width), 3, np.uint8)
    write_capture_set(tmp_path / "dark", CaptureSet(dark, rig.schedule))
    assert main(["change", ref, str(tmp_path / "dark"), "-c",
                 str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o4")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no pixel is valid in both maps" in err
    assert not (tmp_path / "o4").exists()


def test_a_missing_folder_and_a_bad_rate_are_refused(sets, capsys):
    tmp_path, ref, _, _, _ = sets
    assert main(["change", ref, str(tmp_path / "nope"), "-c",
                 str(tmp_path / "calibration.json"), "-o", str(tmp_path / "o5")]) == 2
    assert "not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["change", ref, ref, "-c", "x", "-o", "y", "--false-alarm-rate", "2"])
    assert exc.value.code == 2
