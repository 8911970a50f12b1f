"""Binary PLY of valid points."""

from __future__ import annotations

import numpy as np
import pytest

from app.capture.ply import ply_bytes, read_ply, write_ply


def _cloud():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(6, 7, 3)).astype(np.float32)
    valid = rng.random((6, 7)) > 0.3
    pts[~valid] = np.nan
    return pts, valid


def test_round_trip_valid_points_only(tmp_path):
    pts, valid = _cloud()
    inten = np.arange(42, dtype=np.uint8).reshape(6, 7)
    path = write_ply(tmp_path / "p.ply", pts, valid, inten)
    v = read_ply(path)
    assert v.size == valid.sum()
    assert np.array_equal(np.stack([v["x"], v["y"], v["z"]], 1), pts[valid])
    assert np.array_equal(v["intensity"], inten[valid])
    head = path.read_bytes()[:200].decode("ascii", "replace")
    assert head.startswith("ply\nformat binary_little_endian 1.0\n")
    assert f"element vertex {valid.sum()}\n" in head
    assert (
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar intensity\nend_header\n" in head
    )
    assert len(path.read_bytes()) == head.index("end_header\n") + 11 + 13 * valid.sum()


def test_float_intensity_scaled_and_nan_points_skipped():
    pts, valid = _cloud()
    valid_all = np.ones_like(valid)
    inten = np.linspace(0.0, 2000.0, 42).reshape(6, 7)
    v = read_ply_bytes(ply_bytes(pts, valid_all, inten))
    assert v.size == valid.sum()  # NaN points dropped even if flagged valid
    sel = inten[valid]
    assert v["intensity"].max() == 255
    assert np.allclose(v["intensity"], sel * 255 / sel.max(), atol=0.5 + 1e-9)


def read_ply_bytes(data: bytes):
    end = data.index(b"end_header\n") + 11
    n = int(data.split(b"element vertex ")[1].split(b"\n")[0])
    return np.frombuffer(
        data,
        np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1")]),
        count=n,
        offset=end,
    )


def test_empty_cloud():
    pts, valid = _cloud()
    v = read_ply_bytes(ply_bytes(pts, np.zeros_like(valid), np.zeros((6, 7))))
    assert v.size == 0


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((np.zeros((2, 2)), np.ones((2, 2), bool), np.zeros((2, 2))), "points"),
        ((np.zeros((2, 2, 3)), np.ones((2, 3), bool), np.zeros((2, 2))), "valid"),
        ((np.zeros((2, 2, 3)), np.ones((2, 2)), np.zeros((2, 2))), "valid"),
        ((np.zeros((2, 2, 3)), np.ones((2, 2), bool), np.zeros((3, 2))), "intensity"),
    ],
)
def test_bad_input(args, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        ply_bytes(*args)
