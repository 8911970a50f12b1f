"""Board spec parsing and detection on rendered (perspective-warped) board images."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from app.calib import BoardSpec, detect_board, load_board, texture_to_u8
from tests.helpers.calib_rig import Rig, board_pose, render_board


def _truth(board, rmat, tvec, rig):
    pts, _ = cv2.projectPoints(
        board.object_points(), cv2.Rodrigues(rmat)[0], tvec, rig.camera_matrix, np.zeros(5)
    )
    return pts.reshape(-1, 2)


@pytest.mark.parametrize(
    "board",
    [
        BoardSpec("checkerboard", 9, 6, 3.0),
        BoardSpec("circles", 7, 5, 4.0),
        BoardSpec("asymmetric_circles", 4, 9, 2.5),
    ],
)
def test_detect_board_subpixel(board):
    rig = Rig()
    rmat, tvec = board_pose(board, 95.0, 12.0, -8.0, 5.0)
    img = render_board(board, rmat, tvec, rig)
    det = detect_board(img, board)
    assert det.found
    assert det.image_points.shape == (board.n_points, 2) and det.object_points.shape == (
        board.n_points,
        3,
    )
    truth = _truth(board, rmat, tvec, rig)
    d = np.linalg.norm(det.image_points[:, None, :] - truth[None, :, :], axis=2).min(axis=1)
    assert np.median(d) < 0.1 and d.max() < 0.3


def test_detect_board_not_found():
    board = BoardSpec("checkerboard", 9, 6, 3.0)
    img = np.full((480, 640), 128, np.uint8)
    det = detect_board(img, board)
    assert not det.found and det.image_points.shape == (0, 2)
    with pytest.raises(ValueError, match="^texture_u8"):
        detect_board(img.astype(np.float32), board)


def test_texture_to_u8_scales_and_handles_nan():
    t = np.linspace(0, 1000, 400, dtype=np.float32).reshape(20, 20)
    t[0, 0] = np.nan
    out = texture_to_u8(t)
    assert out.dtype == np.uint8 and out[0, 0] == 0 and out.max() == 255 and out[10, 0] > 100


def test_board_spec_parsing(tmp_path):
    p = tmp_path / "board.json"
    p.write_text(json.dumps({"type": "checkerboard", "inner_corners": [9, 6], "square_mm": 2.0}))
    b = load_board(p)
    assert (b.cols, b.rows, b.pitch_mm) == (9, 6, 2.0)
    assert b.object_points()[10].tolist() == [2.0, 2.0, 0.0]
    a = BoardSpec.from_dict(
        {"type": "asymmetric_circles", "inner_corners": [4, 11], "spacing_mm": 1.0}
    )
    assert a.object_points()[4].tolist() == [1.0, 1.0, 0.0]  # second row offset by one spacing
    assert BoardSpec.from_dict(b.to_dict()) == b
    for bad, msg in [
        ({"type": "hexagons", "inner_corners": [9, 6], "square_mm": 2}, "board.type"),
        ({"type": "checkerboard", "square_mm": 2}, "board.inner_corners"),
        ({"type": "checkerboard", "inner_corners": [9], "square_mm": 2}, "board.inner_corners"),
        ({"type": "checkerboard", "inner_corners": [9, 6]}, "board.square_mm"),
        ({"type": "circles", "inner_corners": [9, 6], "square_mm": 2}, "board.spacing_mm"),
        ({"type": "checkerboard", "inner_corners": [9, 6], "square_mm": -2}, "pitch_mm"),
        ({"type": "checkerboard", "inner_corners": [1, 6], "square_mm": 2}, "inner_corners"),
    ]:
        p.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=msg):
            load_board(p)
    p.write_text("{not json")
    with pytest.raises(ValueError, match="unreadable"):
        load_board(p)
    with pytest.raises(ValueError, match="not found"):
        load_board(tmp_path / "missing.json")
