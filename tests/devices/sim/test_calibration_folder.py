"""Calibration folders: board.json, pose capture sets, boards that OpenCV finds sub-pixel
exactly."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from app.calib.board import detect_board
from app.capture.captureset import read_capture_set
from app.core.board import BoardSpec
from app.devices.sim import default_rig, simulate_calibration_folder
from app.devices.sim.scenes import board_points_mm, sim_board


def _texture(cs) -> np.ndarray:
    mean = cs.frames.astype(np.float32).mean(0)
    return np.clip(mean * (255.0 / mean.max()), 0, 255).astype(np.uint8)


def _truth_corners(cs, spec: BoardSpec, rig) -> np.ndarray:
    sim = cs.extra["simulated"]
    origin, axes = np.array(sim["board_origin_mm"]), np.array(sim["board_axes"])
    pts = origin + board_points_mm(spec) @ axes.T
    return rig.camera.project(pts)


@pytest.mark.slow
def test_checkerboard_folder_detected_subpixel(tmp_path):
    out = simulate_calibration_folder(tmp_path / "cal", board="checkerboard", poses=3, seed=1)
    board = json.loads((out / "board.json").read_text())
    spec, rig = sim_board(), default_rig()
    assert board == {
        "type": "checkerboard",
        "inner_corners": [spec.cols, spec.rows],
        "square_mm": spec.pitch_mm,
    }
    assert BoardSpec.from_dict(board) == spec
    for k in range(3):
        cs = read_capture_set(out / f"pose_{k:02d}")
        assert cs.frames.shape == (16, 1032, 1384) and cs.frames.max() < 255
        # OpenCV's detector with gradient refinement (as calibration runs it): the ±30°
        # poses foreshorten the squares, and raw corners there are off by up to 0.3 px
        det = detect_board(_texture(cs), BoardSpec.from_dict(board))
        ok, corners = det.found, det.image_points
        assert ok, f"pose {k}"
        truth = _truth_corners(cs, spec, rig)
        d = np.linalg.norm(corners.reshape(-1, 2)[:, None, :] - truth[None], axis=2).min(axis=1)
        assert d.mean() < 0.1 and d.max() < 0.3, (k, d.mean(), d.max())
    # pose 0 lies in the reference plane: its truth depth is zero wherever the board is
    depth0 = np.load(out / "pose_00" / "truth_depth.npy")
    assert np.nanmax(np.abs(depth0)) < 1e-4


@pytest.mark.slow
def test_circle_grid_folder_detected(tmp_path):
    out = simulate_calibration_folder(tmp_path / "cal", board="circles", poses=2, seed=2)
    assert json.loads((out / "board.json").read_text())["type"] == "circles"
    spec, rig = sim_board("circles"), default_rig()
    for k in range(2):
        cs = read_capture_set(out / f"pose_{k:02d}")
        ok, centres = cv2.findCirclesGrid(
            _texture(cs), spec.pattern_size, flags=cv2.CALIB_CB_SYMMETRIC_GRID
        )
        assert ok, f"pose {k}"
        truth = _truth_corners(cs, spec, rig)
        d = np.linalg.norm(centres.reshape(-1, 2)[:, None, :] - truth[None], axis=2).min(axis=1)
        assert d.mean() < 0.3, (k, d.mean())
