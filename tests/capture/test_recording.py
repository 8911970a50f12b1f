"""Recordings: round trip, names, zip export, and crashes mid-write that lose nothing."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest
import tifffile

from app.capture import recording as rec_mod
from app.capture.captureset import CaptureSet, read_capture_set
from app.capture.recording import (
    Recording,
    delete_recording,
    depth_npy_bytes,
    depth_tiff_bytes,
    iter_zip,
    list_recordings,
    read_session,
    remove_stale_partials,
    safe_child,
    validate_name,
)

REPO = Path(__file__).resolve().parents[2]


def make_set(seed: int, dtype: type = np.uint8) -> tuple[CaptureSet, np.ndarray]:
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, np.iinfo(dtype).max, size=(16, 24, 32), dtype=dtype)
    depth = rng.uniform(0, 35, size=(24, 32)).astype(np.float32)
    depth[0, :5] = np.nan
    return CaptureSet(frames=frames, exposure_ms=25.0, led="green"), depth


def test_round_trip_sets_and_depth(tmp_path: Path) -> None:
    rec = Recording(tmp_path, "session-1", settings={"exposure_ms": 25.0})
    written = [make_set(i, np.uint8 if i % 2 else np.uint16) for i in range(3)]
    folders = [
        rec.add_set(c, depth_mm=d, timestamp=1_700_000_000 + i) for i, (c, d) in enumerate(written)
    ]
    assert folders == ["set_0000", "set_0001", "set_0002"]
    summary = rec.close()
    assert summary["stopped"] is not None and len(summary["sets"]) == 3

    session = read_session(tmp_path, "session-1")
    assert session["format"] == "fringescope.recording/1"
    assert session["settings"] == {"exposure_ms": 25.0}
    assert session["n_sets"] == 3
    assert session["sets"][1]["timestamp"].startswith("2023-11-14T22:13:21")
    for (cap, depth), folder in zip(written, folders, strict=True):
        back = read_capture_set(tmp_path / "session-1" / folder)
        np.testing.assert_array_equal(back.frames, cap.frames)
        assert back.frames.dtype == cap.frames.dtype
        assert back.exposure_ms == 25.0 and back.extra["index"] == int(folder[-4:])
        np.testing.assert_array_equal(np.load(tmp_path / "session-1" / folder / "depth.npy"), depth)

    (listed,) = list_recordings(tmp_path)
    assert listed["name"] == "session-1" and listed["n_sets"] == 3
    assert listed["bytes"] == sum(
        f.stat().st_size for f in (tmp_path / "session-1").rglob("*") if f.is_file()
    )
    with pytest.raises(ValueError, match="closed"):
        rec.add_set(written[0][0])


def test_names_cannot_escape(tmp_path: Path) -> None:
    for bad in [
        "",
        "../x",
        "..",
        ".hidden",
        "a/b",
        "a\\b",
        "x" * 65,
        "a b",
        "ü",
        "a\n",
        None,
        5,
        "-x",
    ]:
        with pytest.raises(ValueError, match="recording name"):
            validate_name(bad, "recording name")
        with pytest.raises(ValueError):
            Recording(tmp_path, bad)  # type: ignore[arg-type]
    assert validate_name("A.b_c-1") == "A.b_c-1"
    with pytest.raises(ValueError, match=r"\.zip"):
        Recording(tmp_path, "x.zip")
    outside = tmp_path / "outside"
    outside.mkdir()
    root = tmp_path / "root"
    root.mkdir()
    (root / "link").symlink_to(outside)
    with pytest.raises(ValueError, match="outside"):
        safe_child(root, "link")
    with pytest.raises(FileNotFoundError):
        read_session(root, "missing")
    assert set(tmp_path.iterdir()) == {outside, root}  # no refused name left a folder


def test_existing_name_refused(tmp_path: Path) -> None:
    Recording(tmp_path, "a")
    with pytest.raises(FileExistsError, match="already exists"):
        Recording(tmp_path, "a")


def test_zip_streams_whole_recording(tmp_path: Path) -> None:
    rec = Recording(tmp_path, "z")
    sets = [make_set(i) for i in range(2)]
    for cap, depth in sets:
        rec.add_set(cap, depth_mm=depth)
    rec.close()
    chunks = list(iter_zip(tmp_path, "z", chunk_bytes=4096))
    assert len(chunks) > 3 and all(chunks)
    zf = zipfile.ZipFile(io.BytesIO(b"".join(chunks)))
    assert zf.testzip() is None
    names = set(zf.namelist())
    assert "z/session.json" in names and "z/set_0001/frame_15.png" in names
    assert len(names) == 1 + 2 * (16 + 2)
    depth = np.load(io.BytesIO(zf.read("z/set_0001/depth.npy")))
    np.testing.assert_array_equal(depth, sets[1][1])
    with pytest.raises(FileNotFoundError):
        iter_zip(tmp_path, "nope")


def test_depth_exports() -> None:
    depth = np.array([[1.5, np.nan], [0.0, 34.25]], dtype=np.float64)
    back = tifffile.imread(io.BytesIO(depth_tiff_bytes(depth)))
    assert back.dtype == np.float32 and back.shape == (2, 2)
    np.testing.assert_array_equal(back, depth.astype(np.float32))
    np.testing.assert_array_equal(
        np.load(io.BytesIO(depth_npy_bytes(depth))), depth.astype(np.float32)
    )
    with pytest.raises(ValueError, match="depth_mm"):
        depth_tiff_bytes(np.zeros(3))
    with pytest.raises(ValueError, match="depth_mm"):
        depth_npy_bytes(np.zeros((2, 2), dtype=np.uint8))


def test_exception_mid_write_keeps_earlier_sets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = Recording(tmp_path, "r")
    cap0, depth0 = make_set(0)
    rec.add_set(cap0, depth_mm=depth0)
    rec.add_set(make_set(1)[0])
    real_imencode = rec_mod.write_capture_set.__globals__["cv2"].imencode
    calls = {"n": 0}

    def failing_imencode(ext: str, img: np.ndarray, params: list[int]) -> tuple[bool, np.ndarray]:
        calls["n"] += 1
        if calls["n"] == 7:
            raise OSError("disk full (simulated)")
        return real_imencode(ext, img, params)

    monkeypatch.setattr(rec_mod.write_capture_set.__globals__["cv2"], "imencode", failing_imencode)
    with pytest.raises(OSError, match="disk full"):
        rec.add_set(make_set(2)[0])
    monkeypatch.undo()
    assert read_session(tmp_path, "r")["n_sets"] == 2
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == [
        "session.json",
        "set_0000",
        "set_0001",
    ]
    # the session goes on: the next set takes the free slot
    assert rec.add_set(make_set(3)[0]) == "set_0002"
    assert read_session(tmp_path, "r")["n_sets"] == 3


CRASHER = textwrap.dedent(
    """
    import os, signal, sys
    import numpy as np
    import app.capture.captureset as cs
    from app.capture.captureset import CaptureSet
    from app.capture.recording import Recording

    root, where = sys.argv[1], sys.argv[2]
    rec = Recording(root, "crash")
    for i in range(2):
        frames = np.full((16, 24, 32), i + 1, np.uint8)
        rec.add_set(CaptureSet(frames=frames), depth_mm=np.full((24, 32), float(i), np.float32))
    if where == "frames":   # power cut while the 9th PNG of the third set is being written
        real = cs.cv2.imencode
        count = [0]
        def imencode(*a):
            count[0] += 1
            if count[0] == 9:
                os.kill(os.getpid(), signal.SIGKILL)
            return real(*a)
        cs.cv2.imencode = imencode
    else:                   # power cut between writing session.json's temp file and its rename
        import app.atomic as atomic
        real_replace = os.replace
        def replace(src, dst):
            if str(dst).endswith("session.json"):
                os.kill(os.getpid(), signal.SIGKILL)
            return real_replace(src, dst)
        atomic.os.replace = replace
    rec.add_set(CaptureSet(frames=np.full((16, 24, 32), 3, np.uint8)))
    print("not reached")
    """
)


@pytest.mark.parametrize("where", ["frames", "session"])
def test_killed_mid_write_loses_nothing(tmp_path: Path, where: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", CRASHER, str(tmp_path), where],
        cwd=REPO, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == -9, proc.stderr
    assert "not reached" not in proc.stdout
    (summary,) = list_recordings(tmp_path)
    assert summary["name"] == "crash" and summary["n_sets"] == 2
    session = json.loads((tmp_path / "crash" / "session.json").read_text())
    assert [s["folder"] for s in session["sets"]] == ["set_0000", "set_0001"]
    for i in range(2):
        back = read_capture_set(tmp_path / "crash" / f"set_{i:04d}")
        assert (back.frames == i + 1).all()
        assert (np.load(tmp_path / "crash" / f"set_{i:04d}" / "depth.npy") == i).all()
    leftovers = sorted(p.name for p in (tmp_path / "crash").iterdir() if p.name.startswith("."))
    if where == "frames":
        # the third set never appears under its real name: only a hidden partial folder
        assert not (tmp_path / "crash" / "set_0002").exists()
        assert len(leftovers) == 1 and leftovers[0].startswith(".set_0002.")
    else:
        # the set folder was whole, but session.json kept its old, complete content
        assert read_capture_set(tmp_path / "crash" / "set_0002").frames.max() == 3
        assert len(leftovers) == 1 and leftovers[0].startswith(".session.json.")
    names = set(zipfile.ZipFile(io.BytesIO(b"".join(iter_zip(tmp_path, "crash")))).namelist())
    assert not any("set_0002" in n or "/." in n for n in names)
    assert remove_stale_partials(tmp_path) == 1
    assert not any(p.name.startswith(".") for p in (tmp_path / "crash").iterdir())


def test_delete(tmp_path: Path) -> None:
    rec = Recording(tmp_path, "gone")
    rec.add_set(make_set(0)[0])
    rec.close()
    delete_recording(tmp_path, "gone")
    assert list_recordings(tmp_path) == [] and list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError):
        delete_recording(tmp_path, "gone")
    with pytest.raises(ValueError):
        delete_recording(tmp_path, "..")


def test_recover_interrupted_keeps_whole_sets(tmp_path: Path) -> None:
    from app.capture.recording import recover_interrupted

    done = Recording(tmp_path, "done")
    done.add_set(make_set(0)[0])
    done.close()
    open_rec = Recording(tmp_path, "open")  # left open, as by a killed service
    for i in range(3):
        open_rec.add_set(make_set(i)[0], codec="zstd")
    Recording(tmp_path, "empty")
    running = Recording(tmp_path, "running")
    running.add_set(make_set(5)[0])
    # a set folder removed by hand after the crash is not listed; a half-written one never was
    shutil.rmtree(tmp_path / "open" / "set_0002")
    (tmp_path / "open" / ".set_0003.x.partial").mkdir()

    assert recover_interrupted(tmp_path, active="running") == ["empty", "open"]
    listed = {s["name"]: s for s in list_recordings(tmp_path)}
    assert {n: s["interrupted"] for n, s in listed.items()} == {
        "done": False, "empty": True, "open": True, "running": False}
    assert listed["running"]["stopped"] is None
    session = read_session(tmp_path, "open")
    assert session["interrupted"] is True and session["n_sets"] == 2
    assert session["stopped"] == session["sets"][-1]["timestamp"]
    assert read_session(tmp_path, "empty")["stopped"] == read_session(tmp_path, "empty")["started"]
    for s in session["sets"]:
        back = read_capture_set(tmp_path / "open" / s["folder"])
        np.testing.assert_array_equal(back.frames, make_set(int(s["folder"][4:]))[0].frames)
    assert recover_interrupted(tmp_path) == ["running"]  # idempotent for the ones already marked
    assert remove_stale_partials(tmp_path) == 1


def test_zip_stores_zstd_frames_as_they_are(tmp_path: Path) -> None:
    rec = Recording(tmp_path, "z")
    cap, depth = make_set(1)
    rec.add_set(cap, depth_mm=depth, codec="zstd")
    zf = zipfile.ZipFile(io.BytesIO(b"".join(iter_zip(tmp_path, "z"))))
    info = zf.getinfo("z/set_0000/frame_00.npy.zst")
    assert info.compress_type == zipfile.ZIP_STORED
    assert zf.getinfo("z/set_0000/depth.npy").compress_type == zipfile.ZIP_DEFLATED
    assert zf.read(info) == (tmp_path / "z" / "set_0000" / "frame_00.npy.zst").read_bytes()
