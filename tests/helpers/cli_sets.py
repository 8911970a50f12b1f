"""Synthetic capture sets on disk for the command-line tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from app.calib import save_calibration
from app.capture import CaptureSet, write_capture_set
from app.devices.sim.analytic_rig import Rig, bump_surface


def write_bump_set(tmp_path: Path) -> npt.NDArray[np.float64]:
    """A capture set of the analytic rig's bump (``set/``) and its calibration
    (``calibration.json``) under ``tmp_path``; returns the true height map, mm."""
    rig = Rig()
    h = bump_surface(rig)
    frames = rig.render(h, noise=0.5, rng=np.random.default_rng(4))
    frames[:, :8, :8] = 90  # a patch without fringes → invalid
    write_capture_set(tmp_path / "set", CaptureSet(frames, rig.schedule))
    save_calibration(rig.calibration(), tmp_path / "calibration.json")
    return h
