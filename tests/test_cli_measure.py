"""``fringescope measure`` on a synthetic capture set: one JSON line, or exit 2 with one line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.analysis.measure import measure
from app.calib import load_calibration
from app.capture import read_capture_set
from app.cli import main
from app.recon import Reconstructor
from app.recon.noise import estimate_sensor_noise
from app.service.measure import calibration_terms
from tests.helpers.cli_sets import write_bump_set


def _run(tmp_path, capsys, *args):
    rc = main(["measure", str(tmp_path / "set"), "-c", str(tmp_path / "calibration.json"), *args])
    out, err = capsys.readouterr()
    return rc, out, err


def test_measure_prints_one_json_line_matching_the_functions(tmp_path, capsys):
    write_bump_set(tmp_path)
    cal = load_calibration(tmp_path / "calibration.json")
    cap = read_capture_set(tmp_path / "set")
    noise = estimate_sensor_noise(cap.frames, cap.schedule, max_code=cap.max_code)
    res = Reconstructor(cal, noise=noise).run(cap.frames, max_code=cap.max_code)
    h, w = res.valid.shape
    cases = {
        "--length": ("length", [[20, 20], [w - 20, h - 20]]),
        "--point-line": ("point_to_line", [[w // 2, h // 2], [20, 20], [w - 20, 20]]),
        "--depth": ("depth", [[w // 2, h // 2], [20, 20], [w - 20, 20], [w // 2, h - 20]]),
        "--profile": ("profile", [[20, h // 2], [w - 20, h // 2]]),
        "--area": ("area", [[20, 20], [w - 20, 20], [w - 20, h - 20], [20, h - 20]]),
    }
    for flag, (kind, pix) in cases.items():
        rc, out, err = _run(tmp_path, capsys, flag, ",".join(str(c) for p in pix for c in p))
        assert rc == 0, err
        lines = out.strip().splitlines()
        assert len(lines) == 1
        got = json.loads(lines[0])
        ref = measure(kind, res.points, res.valid, res.sigma, pix, plane_normal=cal.plane_normal,
                      calibration_sigma_mm=calibration_terms(cal)[1],
                      calibration_length_mm=calibration_terms(cal)[2])
        assert got["kind"] == kind and got["set"] == "set" and got["noise_source"] == "set"
        assert got["value_mm"] == pytest.approx(ref.value_mm, rel=1e-6)
        assert got["sigma_mm"] == pytest.approx(ref.sigma_mm, rel=1e-6) and got["sigma_mm"] > 0
        assert ("profile" in got) == (kind == "profile")


def test_noise_only_leaves_out_the_calibration_term(tmp_path, capsys):
    write_bump_set(tmp_path)
    cal = load_calibration(tmp_path / "calibration.json")
    with_cal = json.loads(_run(tmp_path, capsys, "--length", "20,20,100,90")[1])
    noise = json.loads(_run(tmp_path, capsys, "--length", "20,20,100,90", "--noise-only")[1])
    assert noise["sigma_mm"] == pytest.approx(with_cal["extra"]["sigma_noise_mm"], rel=1e-9)
    c = calibration_terms(cal)[1]
    expected = (noise["sigma_mm"] if c == 0
                else math.hypot(noise["sigma_mm"], with_cal["extra"]["sigma_calibration_mm"]))
    assert with_cal["sigma_mm"] == pytest.approx(expected, rel=1e-9)


def test_invalid_click_snaps(tmp_path, capsys):
    write_bump_set(tmp_path)  # the 8x8 corner patch has no fringes
    rc, out, _ = _run(tmp_path, capsys, "--length", "7,7,60,60")
    got = json.loads(out)
    assert rc == 0 and got["snapped"] and got["points"][0]["pixel"] != [7, 7]
    assert np.isfinite(got["value_mm"])


@pytest.mark.parametrize(("args", "needle"), [
    (["--length", "3,3,60,60"],
     "point 1 (3, 3): invalid pixel (LOW_MODULATION) and no valid pixel within 3 px"),
    (["--length", "1,2,3"], "expected pairs u,v"),
    (["--length", "10,10"], "needs exactly 2 points, got 1"),
    (["--length=-10,10,20,20"], "point 1 (-10, 10): outside the"),
    (["--depth", "50,50,20,20,30,30,30,30"], "collinear or coincident"),
    (["--area", "20,20,40,40"], "needs at least 3 points"),
    (["--length", "20,20,40,40", "--reference", "1,1,2,2,3,1"], "--reference: only with --profile"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, needle):
    write_bump_set(tmp_path)
    with pytest.raises(SystemExit) if needle == "expected pairs u,v" else _nothing():
        rc, out, err = _run(tmp_path, capsys, *args)
        assert rc == 2 and out == ""
        assert len(err.strip().splitlines()) == 1 and needle in err, err
    if needle == "expected pairs u,v":  # argparse: exit 2 and its usage + one error line
        err = capsys.readouterr().err
        assert needle in err.strip().splitlines()[-1]


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
