"""The calibration file: versioned JSON (writes ``fringescope.calibration/2``; version 1 loads).

The record itself, :class:`~app.core.calibration.Calibration`, lives in :mod:`app.core`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from app.atomic import atomic_write_text
from app.core.calibration import Calibration
from app.core.jsonlimits import check_json_depth

__all__ = ["load_calibration", "save_calibration"]


def save_calibration(calibration: Calibration, path: str | os.PathLike[str]) -> Path:
    """Write ``calibration`` as JSON atomically (old file intact if this fails)."""
    return atomic_write_text(path, json.dumps(calibration.to_dict(), indent=2) + "\n")


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file; ``ValueError`` with the file name for anything wrong."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read calibration ({exc})") from None
    try:
        check_json_depth(text.encode("utf-8"), str(p))
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    try:
        return Calibration.from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from None
