"""``fringescope gamma`` then ``fringescope phase --phase-error`` on real captures (CFPE, see its
README).

The table is learned on one scene's 12-step capture and corrects another scene's 4-step set:
the issue-14 validity target for the plate is met only with it (the raw 4-step plate is
below 95 %; see tests/recon/test_real_cfpe.py).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.capture import CaptureSet, write_capture_set
from app.cli import main
from tests.helpers.cfpe import BUST, CFPE, PLATE, frames, schedule, usable

pytestmark = pytest.mark.skipif(
    not (CFPE / "recordings").is_dir(), reason=f"CFPE real captures not found at {CFPE}"
)


def _write(tmp_path, scene, steps):
    path = tmp_path / f"scene{scene:02d}_{steps}"
    write_capture_set(path, CaptureSet(frames(scene, steps), schedule(steps), bit_depth=8))
    return path


def test_table_learned_on_the_bust_lifts_the_plate_above_95_percent_valid(tmp_path, capsys):
    table = tmp_path / "gamma.json"
    assert main(["gamma", str(_write(tmp_path, BUST, 12)), "-o", str(table), "--steps", "4"]) == 0
    line = capsys.readouterr().out.strip()
    assert "4-step phase error learned against 12 steps" in line and len(line.splitlines()) == 1
    data = json.loads(table.read_text())
    assert data["steps"] == 4 and len(data["error_rad"]) == 3
    plate = _write(tmp_path, PLATE, 4)
    assert main(["phase", str(plate), "-o", str(tmp_path / "raw")]) == 0
    assert (
        main(["phase", str(plate), "-o", str(tmp_path / "corrected"), "--phase-error", str(table)])
        == 0
    )
    use = usable(PLATE)
    raw = float((np.load(tmp_path / "raw" / "reason.npy") == 0)[use].mean())
    corrected = float((np.load(tmp_path / "corrected" / "reason.npy") == 0)[use].mean())
    print(
        f"\ncfpe plate 4-step via the CLI: valid {100 * raw:.2f} % raw, "
        f"{100 * corrected:.2f} % with the bust's table"
    )
    assert corrected >= 0.95 and corrected > raw


def test_a_table_for_another_schedule_is_one_line_and_exit_2(tmp_path, capsys):
    table = tmp_path / "gamma.json"
    assert main(["gamma", str(_write(tmp_path, BUST, 12)), "-o", str(table), "--steps", "6"]) == 0
    capsys.readouterr()
    assert main(["phase", str(_write(tmp_path, PLATE, 4)), "-o", str(tmp_path / "out"),
                 "--phase-error", str(table)]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.count("\n") == 0
        and "steps: the phase-error table corrects 6-step phase, the set has 4" in err
    )
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("content", "expect"),
    [
        (None, "phase-error table not found"),
        ("{", "unreadable phase-error table"),
        ('{"format": "x"}', "format: not a phase-error table"),
    ],
)
def test_bad_table_file_is_one_line_and_exit_2(tmp_path, capsys, content, expect):
    table = tmp_path / "gamma.json"
    if content is not None:
        table.write_text(content)
    assert main(["phase", str(_write(tmp_path, PLATE, 4)), "-o", str(tmp_path / "out"),
                 "--phase-error", str(table)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and expect in err


def test_gamma_refuses_a_reference_that_is_not_a_multiple(tmp_path, capsys):
    assert (
        main(
            [
                "gamma",
                str(_write(tmp_path, BUST, 12)),
                "-o",
                str(tmp_path / "g.json"),
                "--steps",
                "5",
            ]
        )
        == 2
    )
    assert "reference_steps" in capsys.readouterr().err
    assert not (tmp_path / "g.json").exists()
