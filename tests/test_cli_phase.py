"""``fringescope phase`` end to end, and the issue-14 bad inputs of the command line."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from app.calib import save_calibration
from app.capture import CaptureSet, write_capture_set
from app.cli import main
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import PatternSchedule

HET = PatternSchedule(frequencies=(608 / 48, 608 / 45, 608 / 42), steps=4, unwrap="heterodyne")


def _twelve_bit_set(tmp_path, schedule=HET):
    rig = Rig(schedule=schedule)
    h = bump_surface(rig)
    frames = rig.render(
        h,
        background=2000,
        amplitude=1000,
        noise=3.0,
        dtype=np.uint16,
        max_code=4095,
        rng=np.random.default_rng(7),
    )
    frames[:, :8, :8] = 1500  # no fringes → invalid
    write_capture_set(tmp_path / "set", CaptureSet(frames, schedule, bit_depth=12))
    return rig, h


def test_phase_writes_outputs_for_a_12_bit_heterodyne_set(tmp_path, capsys):
    rig, h = _twelve_bit_set(tmp_path)
    out = tmp_path / "out"
    assert main(["phase", str(tmp_path / "set"), "-o", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert (
        len(lines) == 1
        and "heterodyne" in lines[0]
        and "12-bit" in lines[0]
        and "valid" in lines[0]
    )
    phase = np.load(out / "phase.npy")
    modulation = np.load(out / "modulation.npy")
    reason = np.load(out / "reason.npy")
    assert phase.dtype == np.float32 and reason.dtype == np.uint8 and phase.shape == h.shape
    assert np.isnan(phase[:8, :8]).all() and (reason[:8, :8] == 1).all()
    ok = np.isfinite(phase)
    assert ok.mean() > 0.95 and (reason[ok] == 0).all()
    assert np.max(np.abs(phase[ok] - rig.finest_phase(h)[ok])) < 0.05
    assert abs(float(np.median(modulation[ok])) - 1000) < 30
    png = cv2.imread(str(out / "phase.png"))
    assert png is not None and png.shape[2] == 3


def test_12_bit_set_needs_its_bit_depth(tmp_path, capsys):
    """Without ``bit_depth`` the sensor is taken as 16-bit: the validity rule's noise model is then
    that of a 16-bit ADC (σ_I ≈ 100 codes at A = 2000), and B = 1000 is too weak for this
    heterodyne chain: all dropped. An explicit ``--min-modulation`` replaces the rule."""
    _twelve_bit_set(tmp_path)
    meta_path = tmp_path / "set" / "capture.json"
    meta = json.loads(meta_path.read_text())
    del meta["bit_depth"]
    meta_path.write_text(json.dumps(meta))
    assert main(["phase", str(tmp_path / "set"), "-o", str(tmp_path / "out")]) == 0
    assert np.isnan(np.load(tmp_path / "out" / "phase.npy")).all()
    assert (
        main(
            [
                "phase",
                str(tmp_path / "set"),
                "-o",
                str(tmp_path / "out2"),
                "--min-modulation",
                "500",
            ]
        )
        == 0
    )
    reason = np.load(tmp_path / "out2" / "reason.npy")
    assert (reason[:8, :8] == 1).all() and (reason == 0).mean() > 0.9


@pytest.mark.parametrize(("edit", "key"), [
    (lambda m: m.update(bit_depth=10), "bit_depth"),  # 12-bit values in a set declared 10-bit
    (lambda m: m.update(channel="ultraviolet"), "channel"),
    (lambda m: m["pattern"].update(frequencies=[608 / 48, 608 / 42], steps=6), "frequencies"),
    (lambda m: m["pattern"].update(orientation="diagonal"), "orientation"),
])
def test_bad_sets_one_line_naming_the_key_exit_2_nothing_written(tmp_path, capsys, edit, key):
    _twelve_bit_set(tmp_path)
    meta_path = tmp_path / "set" / "capture.json"
    meta = json.loads(meta_path.read_text())
    edit(meta)
    meta_path.write_text(json.dumps(meta))
    out = tmp_path / "out"
    assert main(["phase", str(tmp_path / "set"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_vertical_calibration_on_a_horizontal_set_is_refused(tmp_path, capsys):
    rig = Rig()
    frames = rig.render(bump_surface(rig))
    horizontal = PatternSchedule(orientation="horizontal")
    write_capture_set(tmp_path / "set", CaptureSet(frames, horizontal))
    save_calibration(rig.calibration(), tmp_path / "calibration.json")
    out = tmp_path / "out"
    rc = main(
        [
            "reconstruct",
            str(tmp_path / "set"),
            "-c",
            str(tmp_path / "calibration.json"),
            "-o",
            str(out),
        ]
    )
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pattern.orientation" in err[0] and "'horizontal'" in err[0]
    assert not out.exists()


def test_horizontal_patterns_grow_along_the_projector_height():
    sched = PatternSchedule(
        frequencies=(1, 4), steps=3, width=64, height=48, orientation="horizontal"
    )
    from app.recon import generate_patterns

    pats = generate_patterns(sched).astype(float)
    assert (pats == pats[:, :, :1]).all()  # constant along each row
    row = np.arange(48)
    assert np.allclose(
        pats[3, :, 0], np.rint(255 * (0.5 + 0.5 * np.cos(2 * math.pi * 4 * row / 48)))
    )
