"""The one BoardSpec and its board.json codec."""

from __future__ import annotations

import pytest

from app.core.board import BOARD_TYPES, BoardSpec


@pytest.mark.parametrize("board_type", BOARD_TYPES)
def test_round_trip_writes_design_keys(board_type):
    spec = BoardSpec(board_type, 7, 5, 1.5)
    d = spec.to_dict()
    pitch_key = "square_mm" if board_type == "checkerboard" else "spacing_mm"
    assert d == {"type": board_type, "inner_corners": [7, 5], pitch_key: 1.5}
    assert BoardSpec.from_dict(d) == spec


def test_legacy_grid_key_and_extra_keys_are_read():
    spec = BoardSpec.from_dict(
        {"type": "circles", "grid": [6, 4], "spacing_mm": 2.0, "circle_diameter_mm": 1.0}
    )
    assert spec == BoardSpec("circles", 6, 4, 2.0)


@pytest.mark.parametrize(("bad", "key"), [
    ({"type": "circles", "inner_corners": [6, 4], "square_mm": 2.0}, "board.spacing_mm"),
    ({"type": "checkerboard", "inner_corners": [6, True], "square_mm": 2.0}, "board.inner_corners"),
    ({"type": "checkerboard", "inner_corners": [1, 4], "square_mm": 2.0}, "inner_corners"),
    ([1, 2], "board"),
])
def test_bad_board_names_the_key(bad, key):
    with pytest.raises(ValueError, match=key):
        BoardSpec.from_dict(bad)
