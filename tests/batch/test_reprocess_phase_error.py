"""``--phase-error``: a projector-gamma table learned by ``fringescope gamma`` passes through
``fringescope reconstruct`` and ``fringescope reprocess`` alike (the same bytes per set), and is
part of reprocess's options hash (a run with another table, or none, is not reused)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.calib import save_calibration
from app.capture import CaptureSet, write_capture_set
from app.capture.recording import Recording
from app.cli import main
from app.core.schedule import PatternSchedule
from app.devices.sim.analytic_rig import Rig, bump_surface

FREQS = (1, 4, 12, 36)
FILES = ("depth.npy", "sigma.npy", "reason.png")


def _gamma(frames: np.ndarray, gamma: float = 1.6) -> np.ndarray:
    """A projector with this response exponent: fringes with harmonics an N-step decoder aliases."""
    return np.rint(255.0 * (frames / 255.0) ** gamma).astype(np.uint8)


@pytest.fixture(scope="module")
def gamma_rig(tmp_path_factory):
    """A table from ``fringescope gamma`` on a 12-step set, a 4-set recording and a calibration."""
    tmp = tmp_path_factory.mktemp("gamma")
    rig12 = Rig(schedule=PatternSchedule(FREQS, 12))
    ref = _gamma(rig12.render(bump_surface(rig12), background=120, amplitude=100, noise=0.5))
    write_capture_set(tmp / "ref12", CaptureSet(ref, rig12.schedule, exposure_ms=10.0))
    table = tmp / "gamma.json"
    assert main(["gamma", str(tmp / "ref12"), "-o", str(table), "--steps", "4"]) == 0
    rig = Rig()
    rec = Recording(tmp / "recordings", "rec_gamma", settings={"exposure_ms": 10.0})
    for i in range(4):
        frames = rig.render(bump_surface(rig) + 0.3 * i, background=120, amplitude=100, noise=0.5,
                            rng=np.random.default_rng(i))
        rec.add_set(CaptureSet(_gamma(frames), rig.schedule, exposure_ms=10.0), timestamp=1.7e9 + i)
    rec.close()
    cal = tmp / "calibration.json"
    save_calibration(rig.calibration(), cal)
    return table, rec.path, cal


def _statuses(out: Path, rec: Path) -> set[str]:
    return set(pd.read_parquet(out / rec.name / "sets.parquet")["status"])


@pytest.mark.slow
def test_reconstruct_and_reprocess_apply_the_table_alike(gamma_rig, tmp_path, capsys):
    table, rec, cal = gamma_rig
    assert max(json.loads(table.read_text())["error_rad"][-1], key=abs) != 0.0
    out = tmp_path / "out"
    # an explicit modulation threshold: the set's own noise estimate takes the gamma's harmonics
    # for noise, and the noise-aware rule would then refuse most pixels on either path
    base = ["reprocess", str(rec), "-c", str(cal), "-o", str(out), "--workers", "1", "--quiet",
            "--min-modulation", "10"]
    assert main(base) == 0  # without the table first
    assert _statuses(out, rec) == {"done"}
    plain = {s.name: np.load(s / "depth.npy") for s in sorted((out / rec.name).glob("set_*"))}
    assert main([*base, "--phase-error", str(table)]) == 0  # another option: redone, not reused
    assert "4 done, 0 reused" in capsys.readouterr().out
    assert _statuses(out, rec) == {"done"}
    for name, before in plain.items():
        got = out / rec.name / name
        ref = tmp_path / "ref" / name
        assert main(["reconstruct", str(rec / name), "-c", str(cal), "-o", str(ref),
                     "--min-modulation", "10", "--phase-error", str(table)]) == 0
        for f in FILES:
            assert (got / f).read_bytes() == (ref / f).read_bytes(), f"{name}/{f}"
        depth = np.load(got / "depth.npy")
        ok = np.isfinite(depth) & np.isfinite(before)
        assert ok.mean() > 0.5 and np.abs(depth[ok] - before[ok]).max() > 1e-3  # the table acted
    assert main([*base, "--phase-error", str(table)]) == 0  # the same table: every set reused
    assert "0 done, 4 reused" in capsys.readouterr().out


def test_reprocess_refuses_a_table_of_another_schedule_before_any_work(gamma_rig, tmp_path, capsys):
    _, rec, cal = gamma_rig
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"format": "fringescope-phase-error", "version": 1, "steps": 4,
                                 "frequencies": [1, 4, 12], "bins": 8,
                                 "error_rad": [[0.0] * 8] * 3}))
    out = tmp_path / "out"
    rc = main(["reprocess", str(rec), "-c", str(cal), "-o", str(out), "--phase-error", str(other)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "frequencies: the phase-error table was learned at" in err[0]
    assert not out.exists()
    rc = main(["reconstruct", str(rec / "set_0000"), "-c", str(cal), "-o", str(out),
               "--phase-error", str(other)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "frequencies:" in err[0]
    assert not out.exists()
