"""The calibration board spec and its ``board.json`` codec (DESIGN.md, "Calibration folder")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
import numpy.typing as npt

BoardType = Literal["checkerboard", "circles", "asymmetric_circles"]
BOARD_TYPES: tuple[str, ...] = get_args(BoardType)


@dataclass(frozen=True)
class BoardSpec:
    """A flat calibration target.

    Attributes:
        type: ``"checkerboard"``, ``"circles"`` or ``"asymmetric_circles"``.
        cols, rows: inner corners (checkerboard) or circles per row / per column.
        pitch_mm: square size (checkerboard) or circle spacing, mm. For the asymmetric
            grid, OpenCV's convention: circles in one row are ``2 * pitch_mm`` apart and
            successive rows are offset by ``pitch_mm`` both ways.
    """

    type: BoardType
    cols: int
    rows: int
    pitch_mm: float

    def __post_init__(self) -> None:
        if self.type not in BOARD_TYPES:
            raise ValueError(f"type: must be one of {BOARD_TYPES}, got {self.type!r}")
        integral = int(self.cols) == self.cols and int(self.rows) == self.rows
        if not integral or self.cols < 2 or self.rows < 2:
            raise ValueError(f"inner_corners: need integers >= 2, got [{self.cols}, {self.rows}]")
        if not (math.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise ValueError(f"pitch_mm: must be positive, got {self.pitch_mm}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV pattern size (points per row, points per column)."""
        return (int(self.cols), int(self.rows))

    @property
    def n_points(self) -> int:
        return int(self.cols * self.rows)

    def object_points(self) -> npt.NDArray[np.float32]:
        """(n, 3) float32 board-frame coordinates in mm, z = 0, in OpenCV detection order."""
        i, j = np.mgrid[0 : self.rows, 0 : self.cols]
        if self.type == "asymmetric_circles":
            x = (2 * j + i % 2) * self.pitch_mm
        else:
            x = j * self.pitch_mm
        y = i * self.pitch_mm
        pts = np.stack([x.ravel(), y.ravel(), np.zeros(self.n_points)], axis=1)
        return pts.astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        """The ``board.json`` object (DESIGN.md): ``inner_corners`` [cols, rows] and the pitch key
        of the type."""
        key = "square_mm" if self.type == "checkerboard" else "spacing_mm"
        return {"type": self.type, "inner_corners": [self.cols, self.rows], key: self.pitch_mm}

    @classmethod
    def from_dict(cls, data: Any) -> BoardSpec:
        """Parse a ``board.json`` object; ``ValueError`` names the offending key.

        ``grid`` is read as a synonym of ``inner_corners`` (files written before 2026-11);
        other keys (a circle diameter, say) are ignored.
        """
        if not isinstance(data, dict):
            raise ValueError("board: expected a JSON object")
        btype = data.get("type")
        if btype not in BOARD_TYPES:
            raise ValueError(f"board.type: must be one of {BOARD_TYPES}, got {btype!r}")
        size = data.get("inner_corners", data.get("grid"))
        if size is None:
            raise ValueError("board.inner_corners: missing ([cols, rows])")
        if (
            not isinstance(size, list | tuple)
            or len(size) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) for s in size)
        ):
            raise ValueError(f"board.inner_corners: expected [cols, rows] integers, got {size!r}")
        pitch_key = "square_mm" if btype == "checkerboard" else "spacing_mm"
        pitch = data.get(pitch_key)
        if pitch is None:
            raise ValueError(f"board.{pitch_key}: missing")
        if isinstance(pitch, bool) or not isinstance(pitch, int | float):
            raise ValueError(f"board.{pitch_key}: expected a number, got {pitch!r}")
        try:
            return cls(type=btype, cols=size[0], rows=size[1], pitch_mm=float(pitch))
        except ValueError as exc:
            raise ValueError(f"board: {exc}") from None
