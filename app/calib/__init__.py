"""Calibration: the Eq. (5) coefficients, camera model and reference plane."""

from app.calib.board import BoardSpec, Detection, detect_board, load_board, texture_to_u8
from app.calib.calibration import load_calibration, save_calibration
from app.calib.fitting import (
    CalibrationReport,
    PoseObservation,
    PoseReport,
    calibrate_folder,
    calibrate_sets,
    fit_observations,
    sample_phase,
)
from app.calib.model import height_mm

__all__ = [
    "BoardSpec",
    "CalibrationReport",
    "Detection",
    "PoseObservation",
    "PoseReport",
    "calibrate_folder",
    "calibrate_sets",
    "detect_board",
    "fit_observations",
    "height_mm",
    "load_board",
    "load_calibration",
    "sample_phase",
    "save_calibration",
    "texture_to_u8",
]
