"""Capture-set folders: round trip, missing and mismatched frames, unknown keys."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.capture import CaptureSet, read_capture_set, write_capture_set
from app.recon import PatternSchedule


def _frames(dtype, f=16):
    rng = np.random.default_rng(2)
    return rng.integers(0, np.iinfo(dtype).max, (f, 12, 17), dtype=dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_round_trip(tmp_path, dtype):
    cap = CaptureSet(_frames(dtype), exposure_ms=12.5, led="red", extra={"note": "x"})
    write_capture_set(tmp_path / "s", cap)
    back = read_capture_set(tmp_path / "s")
    assert back.frames.dtype == dtype and np.array_equal(back.frames, cap.frames)
    assert back.schedule == cap.schedule and back.exposure_ms == 12.5 and back.led == "red"
    assert back.extra == {"note": "x"}
    meta = json.loads((tmp_path / "s" / "capture.json").read_text())
    assert meta["format"] == "fringescope.capture/1" and len(meta["frames"]) == 16


def test_unknown_keys_kept(tmp_path):
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint8)))
    meta_path = tmp_path / "s" / "capture.json"
    meta = json.loads(meta_path.read_text())
    meta["operator"] = {"name": "A"}
    meta["pattern"]["gamma"] = 2.2
    meta_path.write_text(json.dumps(meta))
    back = read_capture_set(tmp_path / "s")
    assert back.extra == {"operator": {"name": "A"}}
    assert back.schedule.extra == {"gamma": 2.2}
    write_capture_set(tmp_path / "t", back)
    again = json.loads((tmp_path / "t" / "capture.json").read_text())
    assert again["operator"] == {"name": "A"} and again["pattern"]["gamma"] == 2.2


def test_missing_frame_file(tmp_path):
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint8)))
    (tmp_path / "s" / "frame_07.png").unlink()
    with pytest.raises(ValueError, match="frame_07.png"):
        read_capture_set(tmp_path / "s")


def test_mismatched_shapes_and_dtypes(tmp_path):
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint8)))
    cv2.imwrite(str(tmp_path / "s" / "frame_03.png"), np.zeros((12, 16), np.uint8))
    with pytest.raises(ValueError, match="frame_03.png"):
        read_capture_set(tmp_path / "s")
    cv2.imwrite(str(tmp_path / "s" / "frame_03.png"), np.zeros((12, 17), np.uint16))
    with pytest.raises(ValueError, match="frame_03.png"):
        read_capture_set(tmp_path / "s")


def test_frame_count_and_format_checked(tmp_path):
    with pytest.raises(ValueError, match="^frames"):
        CaptureSet(_frames(np.uint8, f=15))
    assert (
        CaptureSet(_frames(np.uint8, f=12), PatternSchedule(frequencies=(1, 4, 16))).frames.shape[0]
        == 12
    )
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint8)))
    meta_path = tmp_path / "s" / "capture.json"
    meta = json.loads(meta_path.read_text())
    meta["frames"] = meta["frames"][:-1]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="capture.json"):
        read_capture_set(tmp_path / "s")
    meta["format"] = "fringescope.capture/2"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="unsupported format"):
        read_capture_set(tmp_path / "s")
    with pytest.raises(ValueError, match="not a capture-set folder"):
        read_capture_set(tmp_path / "nope")


def test_bit_depth_round_trip_and_max_code(tmp_path):
    frames = _frames(np.uint16) >> 4  # 12-bit codes in 16-bit frames
    cap = CaptureSet(frames, bit_depth=12)
    assert cap.max_code == 4095 and CaptureSet(frames).max_code == 65535
    write_capture_set(tmp_path / "s", cap)
    assert json.loads((tmp_path / "s" / "capture.json").read_text())["bit_depth"] == 12
    back = read_capture_set(tmp_path / "s")
    assert back.bit_depth == 12 and back.max_code == 4095 and "bit_depth" not in back.extra


@pytest.mark.parametrize(("key", "value", "message"), [
    ("bit_depth", 10, "bit_depth: frames hold values up to"),
    ("bit_depth", 11, "bit_depth: must be one of"),
    ("channel", "infrared", "channel: must be one of"),
])
def test_bad_format_keys_name_the_key(tmp_path, key, value, message):
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint16)))
    meta_path = tmp_path / "s" / "capture.json"
    meta = json.loads(meta_path.read_text())
    meta[key] = value
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=message):
        read_capture_set(tmp_path / "s")


@pytest.mark.parametrize(("led", "channel", "plane"), [
    ("red", None, 2), ("blue", None, 0), ("green", "red", 2), ("green", "luminance", None)])
def test_colour_frames_decode_one_channel(tmp_path, led, channel, plane):
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint8), led=led))
    rng = np.random.default_rng(3)
    colour = rng.integers(0, 256, (16, 12, 17, 3), dtype=np.uint8)
    for i in range(16):  # frames stay on disk as a colour camera wrote them
        cv2.imwrite(str(tmp_path / "s" / f"frame_{i:02d}.png"), colour[i])
    meta_path = tmp_path / "s" / "capture.json"
    meta = json.loads(meta_path.read_text())
    if channel:
        meta["channel"] = channel
    meta_path.write_text(json.dumps(meta))
    back = read_capture_set(tmp_path / "s")
    assert back.frames.shape == (16, 12, 17) and back.channel == (channel or led)
    if plane is None:
        expected = np.stack([cv2.cvtColor(c, cv2.COLOR_BGR2GRAY) for c in colour])
    else:
        expected = colour[..., plane]
    assert np.array_equal(back.frames, expected)


def test_heterodyne_and_horizontal_pattern_keys(tmp_path):
    sched = PatternSchedule(
        frequencies=(1920 / 48, 1920 / 45, 1920 / 42),
        steps=3,
        width=1920,
        height=1080,
        orientation="horizontal",
        unwrap="heterodyne",
    )
    assert sched.axis_length == 1080
    write_capture_set(tmp_path / "s", CaptureSet(_frames(np.uint8, 9), schedule=sched))
    back = read_capture_set(tmp_path / "s")
    assert back.schedule == sched and back.schedule.unwrap == "heterodyne"
    meta = json.loads((tmp_path / "s" / "capture.json").read_text())
    meta["pattern"]["frequencies"] = [40, 42.5]
    (tmp_path / "s" / "capture.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="frequencies: heterodyne unwrapping needs at least 3"):
        read_capture_set(tmp_path / "s")


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_zstd_frames_round_trip_bit_exact(tmp_path: Path, dtype: type) -> None:
    rng = np.random.default_rng(3)
    top = np.iinfo(dtype).max
    frames = rng.integers(0, top, size=(16, 40, 56), dtype=dtype, endpoint=True)
    frames[:, :, 0], frames[:, :, -1] = top, 0  # the differences wrap both ways
    cap = CaptureSet(frames=frames, exposure_ms=12.5, led="blue", extra={"note": "kept"})
    write_capture_set(tmp_path / "s", cap, codec="zstd")
    names = sorted(p.name for p in (tmp_path / "s").iterdir())
    assert names == ["capture.json", *[f"frame_{i:02d}.npy.zst" for i in range(16)]]
    back = read_capture_set(tmp_path / "s")
    assert back.frames.dtype == frames.dtype
    np.testing.assert_array_equal(back.frames, frames)
    assert (back.exposure_ms, back.led, back.extra["note"]) == (12.5, "blue", "kept")


def test_zstd_frame_refused_with_its_name(tmp_path: Path) -> None:
    import zstandard

    from app.capture.captureset import MAX_FRAME_BYTES

    cap = CaptureSet(frames=np.zeros((16, 8, 8), np.uint8))
    write_capture_set(tmp_path / "s", cap, codec="zstd")
    bad = tmp_path / "s" / "frame_03.npy.zst"
    bad.write_bytes(b"not zstd at all")
    with pytest.raises(ValueError, match="frame_03.npy.zst: not a zstd frame"):
        read_capture_set(tmp_path / "s")
    # a bomb: a small file that would decompress beyond the bound is refused before decompressing
    bad.write_bytes(zstandard.ZstdCompressor(level=19).compress(bytes(MAX_FRAME_BYTES + 1)))
    assert bad.stat().st_size < 1 << 20
    with pytest.raises(ValueError, match="frame_03.npy.zst: decompressed size"):
        read_capture_set(tmp_path / "s")
    bad.write_bytes(zstandard.ZstdCompressor().compress(b"\x93NUMPY garbage"))
    with pytest.raises(ValueError, match="frame_03.npy.zst: unreadable frame"):
        read_capture_set(tmp_path / "s")
    with pytest.raises(ValueError, match="codec"):
        write_capture_set(tmp_path / "t", cap, codec="jpeg")


def test_zstd_set_with_a_frame_of_another_shape_or_payload_is_refused(tmp_path: Path) -> None:
    import io

    import zstandard

    from app.capture.captureset import zstd_frame_bytes

    frames = np.random.default_rng(5).integers(0, 255, size=(16, 12, 20), dtype=np.uint8)
    write_capture_set(tmp_path / "s", CaptureSet(frames=frames), codec="zstd")
    bad = tmp_path / "s" / "frame_07.npy.zst"
    # decoded in place into the stack when it fits; a frame that does not is named, not written
    bad.write_bytes(zstd_frame_bytes(frames[7, :, :10].copy()))
    with pytest.raises(ValueError, match=r"frame_07.npy.zst: \(12, 10\) uint8 differs from"):
        read_capture_set(tmp_path / "s")
    bad.write_bytes(zstd_frame_bytes(frames[7].astype(np.uint16)))
    with pytest.raises(ValueError, match=r"frame_07.npy.zst: \(12, 20\) uint16 differs"):
        read_capture_set(tmp_path / "s")
    raw = io.BytesIO()
    np.save(raw, frames[7])
    bad.write_bytes(zstandard.ZstdCompressor().compress(raw.getvalue()[:-5]))  # a short payload
    with pytest.raises(ValueError, match="frame_07.npy.zst: unreadable frame .*data bytes for"):
        read_capture_set(tmp_path / "s")
    raw = io.BytesIO()
    np.save(raw, np.asfortranarray(frames[7]))
    bad.write_bytes(zstandard.ZstdCompressor().compress(raw.getvalue()))
    with pytest.raises(ValueError, match="frame_07.npy.zst: unreadable frame .*C-ordered"):
        read_capture_set(tmp_path / "s")
    bad.write_bytes(zstd_frame_bytes(frames[7]))
    np.testing.assert_array_equal(read_capture_set(tmp_path / "s").frames, frames)
