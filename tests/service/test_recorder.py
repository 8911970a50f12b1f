"""The recorder's collector and writer threads on real slots, frame sets and disk.

The instrument here is the recorder's view of one (``RecordedInstrument``): the two
public slots the live pipeline publishes into, fed by the test at the camera's pace.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from app.capture.captureset import read_capture_set
from app.capture.recording import Recording, list_recordings, recordings_root
from app.config import Settings
from app.core.schedule import PatternSchedule, schedule_by_name
from app.devices.base import Frame
from app.service.framesets import FrameSet
from app.service.reconstruction import LiveResult
from app.service.recorder import Recorder
from app.service.store import LatestSlot

H, W = 48, 64


class _Acquisition:
    def __init__(self) -> None:
        self.sets: LatestSlot[FrameSet] = LatestSlot()
        self.alive = True


class _Instrument:
    def __init__(self, data_dir: Path, schedule: PatternSchedule) -> None:
        self.settings = Settings(data_dir=data_dir, viewer=False)
        self.schedule = schedule
        self.acquisition: Any = _Acquisition()
        self.results: LatestSlot[LiveResult] = LatestSlot()


def _frame_set(k: int, n: int, rng: np.random.Generator) -> FrameSet:
    t0 = time.monotonic()
    frames = tuple(Frame(data=rng.integers(0, 256, (H, W), dtype=np.uint8), index=k * n + i,
                         timestamp=t0 + 1e-3 * i, pattern_index=i, exposure_ms=30.0, led="green")
                   for i in range(n))
    return FrameSet(frames=frames, received_s=t0)


def _result(fs: FrameSet, k: int) -> LiveResult:
    depth = np.full((H, W), float(k), np.float32)
    pts = np.zeros((H, W, 3), np.float32)
    now = time.monotonic()
    return LiveResult(depth=depth, points=pts, valid=np.ones((H, W), bool),
                      reason=np.zeros((H, W), np.uint8), texture=np.zeros((H, W), np.float32),
                      modulation=np.zeros((H, W), np.float32), motion=None, mode="set",
                      frame_indices=fs.frame_indices, timestamps=fs.timestamps, exposure_ms=30.0,
                      led="green", full_scale=255.0, received_s=fs.received_s, published_s=now,
                      recon_ms=1.0, seq=k)


def test_every_set_at_the_camera_pace_is_written_with_its_depth(tmp_path: Path) -> None:
    schedule = schedule_by_name("geometric-9")
    inst = _Instrument(tmp_path, schedule)
    rec = Recorder(inst, min_free_mb=0, depth_wait_s=0.3)  # type: ignore[arg-type]
    rng = np.random.default_rng(0)
    rec.start("pace")
    published: list[FrameSet] = []
    for k in range(60):  # 5 sets/s (geometric-9 at 30 ms: 3.7); every other one reconstructed
        fs = _frame_set(k, schedule.n_frames, rng)
        inst.acquisition.sets.publish(fs)
        published.append(fs)
        if k % 2 == 0:
            inst.results.publish(_result(fs, k))
        time.sleep(0.2)
    deadline = time.monotonic() + 30
    while rec.status()["sets"] < 60 and time.monotonic() < deadline:
        time.sleep(0.05)
    session = rec.stop()
    assert session is not None
    st = rec.status()
    assert st["skipped_sets"] == 0 and st["errors"] == 0 and st["last_error"] is None
    assert len(session["sets"]) == 60 and st["sets_with_depth"] == 30
    assert st["write_cpu_ms_per_set"] > 0 and 1 <= st["queue_peak"] <= 16
    root = recordings_root(tmp_path) / "pace"
    for k, (entry, fs) in enumerate(zip(session["sets"], published, strict=True)):
        cap = read_capture_set(root / entry["folder"])  # zstd frames, read back bit-exact
        np.testing.assert_array_equal(cap.frames, fs.stack())
        assert cap.extra["frame_indices"] == fs.frame_indices
        assert entry["depth"] == (k % 2 == 0)
        if entry["depth"]:
            assert (np.load(root / entry["folder"] / "depth.npy") == k).all()
    assert json.loads((root / "session.json").read_text())["stopped"] is not None


def test_the_writer_never_holds_up_the_collector(tmp_path: Path) -> None:
    """A disk that stalls: the queues fill, later sets are counted as skipped, and the
    collector keeps taking sets off the slot (it never waits on the writer)."""
    schedule = schedule_by_name("geometric-9")
    inst = _Instrument(tmp_path, schedule)
    rec = Recorder(inst, min_free_mb=0, depth_wait_s=0.0, queue_sets=3)  # type: ignore[arg-type]
    gate = threading.Event()
    real_store = rec._store

    def slow_disk(*args: Any) -> None:  # the disk stalls until the test opens the gate
        gate.wait(30)
        real_store(*args)

    rec._store = slow_disk  # type: ignore[method-assign]
    rng = np.random.default_rng(1)
    rec.start("stalled")
    for k in range(12):
        inst.acquisition.sets.publish(_frame_set(k, schedule.n_frames, rng))
        time.sleep(0.05)
    time.sleep(0.5)
    st = rec.status()
    # one set at the disk, two encoded behind it, one in the encoder's hands, three queued:
    # the rest counted as they arrived
    assert st["sets"] == 0 and st["queue_peak"] == 3 and st["skipped_sets"] == 12 - 1 - 2 - 1 - 3
    gate.set()
    session = rec.stop()
    assert session is not None and len(session["sets"]) == 7
    assert rec.status()["skipped_sets"] == 5


def test_start_up_marks_open_recordings_interrupted_and_removes_partials(tmp_path: Path) -> None:
    schedule = schedule_by_name("geometric-9")
    inst = _Instrument(tmp_path, schedule)
    root = recordings_root(tmp_path)
    left = Recording(root, "left-open")
    fs = _frame_set(0, schedule.n_frames, np.random.default_rng(2))
    from app.capture.captureset import CaptureSet

    left.add_set(CaptureSet(frames=fs.stack(), schedule=schedule), codec="zstd")
    (root / "left-open" / ".set_0001.abc.partial").mkdir()
    rec = Recorder(inst, min_free_mb=0)  # type: ignore[arg-type]
    assert rec.recovered == ["left-open"]
    assert not (root / "left-open" / ".set_0001.abc.partial").exists()
    (summary,) = list_recordings(root)
    assert summary["interrupted"] is True and summary["n_sets"] == 1


def test_the_change_service_given_to_the_recorder_stores_each_sets_change(
        tmp_path: Path) -> None:
    """The recorder gets the change service as a constructor argument: with a reference set,
    every set with a depth map is stored with the change map the service made of it."""
    from app.devices.sim.analytic_rig import Rig
    from app.service.change import ChangeService

    cal = Rig(width=W, height=H).calibration()
    changes = ChangeService(tmp_path / "reference", lambda: cal)
    schedule = schedule_by_name("geometric-9")
    inst = _Instrument(tmp_path, schedule)
    inst.results.subscribe(changes.on_map)
    changes.start()
    flat = np.zeros((H, W), np.float32)
    changes.set_reference(flat, np.full((H, W), 0.05, np.float32),
                          np.zeros((H, W, 3), np.float32), {"kind": "upload"})
    rec = Recorder(inst, min_free_mb=0, depth_wait_s=0.5,  # type: ignore[arg-type]
                   changes=changes)
    rng = np.random.default_rng(0)
    rec.start("withchange")
    for k in range(4):
        fs = _frame_set(k, schedule.n_frames, rng)
        inst.acquisition.sets.publish(fs)
        res = _result(fs, k)
        res.depth = flat + 0.05 * rng.standard_normal((H, W)).astype(np.float32)
        res.depth[10:20, 20:30] += 1.0 + k  # a local rise: a fixed-scope change map
        res.sigma = np.full((H, W), 0.05, np.float32)
        res.seq = inst.results.publish(res)  # as the reconstruction thread numbers it
        time.sleep(0.3)
    deadline = time.monotonic() + 30
    while rec.status()["sets"] < 4 and time.monotonic() < deadline:
        time.sleep(0.05)
    session = rec.stop()
    changes.close(5.0)
    assert session is not None and len(session["sets"]) == 4
    root = recordings_root(tmp_path) / "withchange"
    stored = [e for e in session["sets"] if (root / e["folder"] / "change.npy").is_file()]
    assert stored, "no set was stored with its change map"
    for entry in stored:
        depth = np.load(root / entry["folder"] / "depth.npy")
        delta = np.load(root / entry["folder"] / "change.npy")
        assert delta.dtype == np.float32 and entry["change"] == "fixed"
        np.testing.assert_allclose(delta, depth - flat)
        assert delta[10:20, 20:30].min() > 0.5
