"""The calibration file: round trip, versions, missing keys, image size, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest

import app.atomic
from app.calib import load_calibration, save_calibration
from app.core.calibration import Calibration
from app.devices.sim.analytic_rig import Rig


@pytest.fixture
def cal() -> Calibration:
    c = Rig().calibration(height_range_mm=(0.0, 28.5))
    c.dist_coeffs = np.array([-0.1, 0.01, 0.0, 0.0, 0.0])
    c.pose_residuals = [{"pose": 0, "rms_mm": 0.01, "reprojection_px": 0.2, "points": 54}]
    return c


def test_round_trip(tmp_path, cal):
    path = save_calibration(cal, tmp_path / "calibration.json")
    back = load_calibration(path)
    for name in ("camera_matrix", "dist_coeffs", "plane_normal", "numerator", "denominator"):
        assert np.array_equal(getattr(back, name), getattr(cal, name)), name
    assert back.image_size == cal.image_size and back.plane_offset_mm == cal.plane_offset_mm
    assert back.normalization == cal.normalization and back.pattern == cal.pattern
    assert back.height_range_mm == (0.0, 28.5) and back.pose_residuals == cal.pose_residuals
    assert back.created == cal.created
    data = json.loads(path.read_text())
    assert data["format"] == "fringescope.calibration/2"
    assert len(data["model"]["numerator"]) + len(data["model"]["denominator"]) == 23


def test_unknown_keys_kept(tmp_path, cal):
    path = save_calibration(cal, tmp_path / "c.json")
    data = json.loads(path.read_text())
    data["site"] = "OR 3"
    path.write_text(json.dumps(data))
    back = load_calibration(path)
    assert back.extra == {"site": "OR 3"}
    assert json.loads(save_calibration(back, tmp_path / "d.json").read_text())["site"] == "OR 3"


def test_wrong_format_version(tmp_path, cal):
    data = cal.to_dict()
    data["format"] = "fringescope.calibration/3"
    (tmp_path / "c.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="c.json.*unsupported format"):
        load_calibration(tmp_path / "c.json")


@pytest.mark.parametrize(
    "drop", ["camera_matrix", "model", "model.numerator", "reference_plane.offset_mm", "pattern"]
)
def test_missing_keys(tmp_path, cal, drop):
    data = cal.to_dict()
    if "." in drop:
        outer, inner = drop.split(".")
        del data[outer][inner]
    else:
        del data[drop]
    (tmp_path / "c.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=f"missing keys.*{drop}"):
        load_calibration(tmp_path / "c.json")


def test_nan_and_garbage(tmp_path, cal):
    data = cal.to_dict()
    data["model"]["numerator"][3] = float("nan")
    (tmp_path / "c.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="numerator"):
        load_calibration(tmp_path / "c.json")
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_calibration(tmp_path / "c.json")
    with pytest.raises(ValueError, match="not found"):
        load_calibration(tmp_path / "missing.json")


def test_image_size_mismatch(cal):
    w, h = cal.image_size
    cal.check_frames((16, h, w))
    with pytest.raises(ValueError, match="^frames: image size"):
        cal.check_frames((16, h, w + 2))
    with pytest.raises(ValueError, match="^frames: expected 16 frames"):
        cal.check_frames((12, h, w))


def test_atomic_write_keeps_old_file(tmp_path, cal, monkeypatch):
    path = save_calibration(cal, tmp_path / "calibration.json")
    old = path.read_bytes()
    cal.plane_offset_mm = 99.0

    def broken_fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr(app.atomic.os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        save_calibration(cal, path)
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json"]  # no temp file left


@pytest.mark.parametrize("size", [[True, 1032], ["1384", 1032], [1384.5, 1032], [1384]])
def test_an_image_size_is_two_integers(tmp_path, cal, size):
    """A file's ``true`` or ``"1384"`` is not a width (``int()`` would read them as 1 and 1384)."""
    path = save_calibration(cal, tmp_path / "c.json")
    data = json.loads(path.read_text())
    data["image_size"] = size
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="calibration: image_size: must be two integers"):
        load_calibration(path)
    data["image_size"] = [float(cal.image_size[0]), cal.image_size[1]]  # 1384.0 is 1384
    path.write_text(json.dumps(data))
    assert load_calibration(path).image_size == cal.image_size
