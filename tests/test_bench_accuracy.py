"""bench_accuracy.py reports a target it cannot measure as a miss instead of crashing: a
calibration under which the DOF target has no valid pixel (here: all frames dark)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

from app.devices.sim.ideal import true_geometric_calibration
from app.devices.sim.optics import default_rig
from app.recon import Reconstructor

ROOT = Path(__file__).resolve().parents[1]


def _bench():  # noqa: ANN202
    path = ROOT / "benchmarks" / "bench_accuracy.py"
    spec = importlib.util.spec_from_file_location("bench_accuracy", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_accuracy"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_a_plane_without_valid_pixels_is_a_reported_miss(capsys):  # noqa: ANN001
    bench = _bench()
    rig = default_rig()
    cal = true_geometric_calibration(rig)
    w, h = cal.image_size
    frames = np.zeros((cal.pattern.n_frames, h, w), np.uint8)
    res = Reconstructor(cal, max_code=255).run(frames)
    assert not res.valid.any()
    truth = np.full((h, w), 5.0)
    assert bench._plane_report(cal, res, truth, 1.0, "DOF target") is None
    assert "DOF target: no plane fit" in capsys.readouterr().out
    rows = bench._plane_rows(None, None)
    assert [r[1] for r in rows] == ["no depth", "no depth"]
    assert all(r[4] is False for r in rows)  # each counts as a missed target


def test_model_dominated_ninths_are_pooled_and_set_against_what_an_honest_sigma_gives() -> None:
    bench = _bench()
    noise_only = (5000, 1.0, 0.0, 0.005, 0.1)
    model = [(5000, 0.5, 0.01, 0.04, 1.0), (5000, 0.5, -0.01, 0.04, 1.0)]
    rows = [
        {"rig": "a", "scenes": {"s": {"cells": [noise_only, *model]}}},
        {"rig": "b", "error": "calibration refused"},
    ]
    text = bench.model_dominated_summary(rows)
    assert "ninths where sigma_model dominates sigma (sigma_model^2 > sigma_noise^2): 2 " in text
    assert "pooled RMS(error/sigma) 0.50" in text
    # all model: RMS(e/σ) = |ζ|, in 0.85-1.15 for 2(Φ(1.15) − Φ(0.85)) = 14.5 % of ninths
    assert "(an honest sigma_model: ~14%)" in text or "(an honest sigma_model: ~15%)" in text
    assert bench.model_dominated_summary(rows[1:]).endswith("none")
