"""Calibration: the Eq. (5) coefficients, camera model and reference plane."""

from app.calib.calibration import Calibration, load_calibration, save_calibration

__all__ = ["Calibration", "load_calibration", "save_calibration"]
