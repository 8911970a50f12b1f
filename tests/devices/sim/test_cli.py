"""``fringescope simulate`` command line."""

from __future__ import annotations

import json

import numpy as np

from app.capture.captureset import read_capture_set
from app.cli import main


def test_list(capsys):
    assert main(["simulate", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    described = dict(line.split(": ", 1) for line in lines)  # one "name: description" a line
    assert {"plane", "dof_target", "skin_flap", "intestine_flap", "intestine_pile", "anastomosis",
            "sphere", "calibration"} <= set(described)
    assert all("surface" in text and " mm" in text for name, text in described.items()
               if name != "calibration")


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    assert main(["simulate", "nowhere", "-o", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "scene" in err
    assert main(["simulate", "plane"]) == 2
    assert main(["simulate", "calibration", "-o", str(tmp_path), "--poses", "1"]) == 2
    assert main(["simulate", "plane", "-o", str(tmp_path), "--exposure-ms", "500"]) == 2
    assert main(["simulate", "plane", "-o", str(tmp_path), "--frames-per-second", "200"]) == 2


def test_writes_sets_with_truth(tmp_path, plane_world):
    out = tmp_path / "sets"
    # 12-bit, 2 sets: 16 frames at 40 ms → 0.64 s a set
    assert (
        main(
            [
                "simulate",
                "plane",
                "-o",
                str(out),
                "--bits",
                "12",
                "--seed",
                "3",
                "--exposure-ms",
                "40",
                "--duration-s",
                "1.3",
                "--no-distortion",
            ]
        )
        == 0
    )
    sets = sorted(p.name for p in out.iterdir())
    assert sets == ["set_0000", "set_0001"]
    cs = read_capture_set(out / "set_0001")
    assert cs.frames.dtype == np.uint16 and cs.frames.max() <= 4095 and cs.exposure_ms == 40.0
    depth = np.load(out / "set_0001" / "truth_depth.npy")
    points = np.load(out / "set_0001" / "truth_points.npy")
    assert depth.shape == (1032, 1384) and points.shape == (1032, 1384, 3)
    assert depth.dtype == np.float32 and 5 < np.nanmedian(depth) < 15
    meta = json.loads((out / "set_0001" / "capture.json").read_text())
    assert meta["simulated"]["scene"] == "plane" and meta["simulated"]["t0_s"] > 0.6
