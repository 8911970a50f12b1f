"""The twin's projector defect options: radial lens distortion across the fringes and an
uncorrected DMD gamma, off by default, on in the ``<preset>-projector-defect`` variants."""

from __future__ import annotations

import numpy as np
import pytest

from app.devices.sim import default_rig, projector_defect_rig, rig_by_name
from app.devices.sim.optics import DEFECT_GAMMA, DEFECT_RADIAL


def _points_on_column(rig, col_px: float, rows_px: np.ndarray,
                      depth_mm: float = 40.0) -> np.ndarray:
    """Camera-frame points the pinhole projector sends to DMD column ``col_px`` at ``rows_px``."""
    p = rig.projector
    y = (rows_px - p.K[1, 2]) / p.K[1, 1]
    x = np.full_like(y, (col_px - p.K[0, 2]) / p.K[0, 0])
    q = np.stack([x, y, np.ones_like(y)], axis=-1) * depth_mm
    return q @ p.R.T + p.centre


def test_off_by_default():
    rig = default_rig()
    assert rig.projector.radial == (0.0, 0.0) and rig.projector_gamma == 1.0
    pts = _points_on_column(rig, 500.0, np.array([10.0, 341.5, 670.0]))
    np.testing.assert_allclose(rig.projector.column(pts), 500.0, atol=1e-9)


def test_defect_bends_the_fringes_and_keeps_the_rest():
    base = default_rig()
    rig = rig_by_name("default-projector-defect")
    assert rig.name == "default-projector-defect"
    assert rig.projector.radial == DEFECT_RADIAL and rig.projector_gamma == DEFECT_GAMMA
    assert rig.camera is base.camera or np.array_equal(rig.camera.K, base.camera.K)
    assert np.array_equal(rig.projector.centre, base.projector.centre)
    rows = np.array([10.0, 341.5, 670.0])
    col = rig.projector.column(_points_on_column(base, 500.0, rows))
    # a straight pinhole column is bent: its distorted column depends on the row (no 1-D model)
    assert col[1] > 500.0 and col[0] - col[1] > 2.0 and col[2] - col[1] > 2.0
    centre = rig.projector.column(_points_on_column(base, 303.5, rows))
    np.testing.assert_allclose(centre, 303.5, atol=1e-9)  # the axis stays put


def test_defect_arguments():
    with pytest.raises(ValueError, match="^gamma"):
        projector_defect_rig(default_rig(), gamma=0.0)
    with pytest.raises(ValueError, match="^radial"):
        projector_defect_rig(default_rig(), radial=(float("nan"), 0.0))
    with pytest.raises(ValueError, match="^rig: unknown 'nope-projector-defect'"):
        rig_by_name("nope-projector-defect")
