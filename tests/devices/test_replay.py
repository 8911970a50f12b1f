"""Replay of a recorded session (capture-set folders) as a camera."""

from __future__ import annotations

import time

import pytest

from app.devices import DeviceDisconnected, DeviceNotFound, DeviceState, DeviceTimeout
from app.devices.replay import ReplayCamera, find_capture_sets
from tests.helpers.recordings import H, N, W, make_recording


def test_frames_in_recorded_order_with_pattern_indices_and_loop(tmp_path):
    rec = make_recording(tmp_path / "rec")
    assert [p.name for p in find_capture_sets(rec)] == ["set_0000", "set_0001"]
    cam = ReplayCamera(rec, pace=False)
    assert (cam.capabilities.width, cam.capabilities.height) == (W, H)
    cam.open()
    cam.start()
    frames = [cam.grab(1.0) for _ in range(2 * N + 2)]
    cam.close()
    values = [int(f.data[0, 0]) for f in frames]
    assert values == list(range(2 * N)) + [0, 1]
    assert [f.pattern_index for f in frames] == [j % N for j in range(2 * N + 2)]
    assert [f.index for f in frames] == list(range(2 * N + 2))
    ts = [f.timestamp for f in frames]
    assert all(b > a for a, b in zip(ts, ts[1:], strict=False))
    assert (
        frames[0].meta["set"] == "set_0000"
        and frames[0].exposure_ms == 20.0
        and frames[0].led == "green"
    )


def test_single_capture_set_folder_replays(tmp_path):
    rec = make_recording(tmp_path / "rec", n_sets=1)
    cam = ReplayCamera(rec / "set_0000", pace=False, loop=False)
    cam.open()
    cam.start()
    assert [int(cam.grab(1.0).data[0, 0]) for _ in range(N)] == list(range(N))
    with pytest.raises(DeviceTimeout, match="end of recording"):
        cam.grab(0.1)
    cam.close()


@pytest.mark.serial
def test_paced_by_recorded_timestamps_and_speed(tmp_path):
    rec = make_recording(tmp_path / "rec", n_sets=1, timestamps=True)
    for speed, expected_s in ((1.0, 0.450), (3.0, 0.150)):
        cam = ReplayCamera(rec, speed=speed, loop=False)
        cam.open()
        cam.start()
        cam.grab(1.0)
        t0 = time.monotonic()
        for _ in range(15):
            cam.grab(1.0)
        elapsed = time.monotonic() - t0
        cam.close()
        # loaded CI sleeps late
        assert expected_s - 0.005 < elapsed < expected_s + 0.2, (speed, elapsed)


def test_paced_by_exposure_without_timestamps_and_timeout(tmp_path):
    rec = make_recording(tmp_path / "rec", n_sets=1, exposure_ms=40.0)
    cam = ReplayCamera(rec, gap_ms=10.0)
    cam.open()
    cam.start()
    cam.grab(1.0)
    t0 = time.monotonic()
    cam.grab(1.0)
    assert 0.045 < time.monotonic() - t0 < 0.1  # 40 ms exposure + 10 ms gap
    with pytest.raises(DeviceTimeout):
        cam.grab(0.01)  # next frame is ~50 ms away
    cam.close()


def test_recording_vanishing_is_a_disconnect_and_reopen_recovers(tmp_path):
    rec = make_recording(tmp_path / "rec")
    cam = ReplayCamera(rec, pace=False)
    cam.open()
    cam.start()
    cam.grab(1.0)
    rec.rename(tmp_path / "moved")
    with pytest.raises(DeviceDisconnected, match="unreadable"):
        for _ in range(N):
            cam.grab(1.0)
    assert cam.state is DeviceState.FAULT and cam.last_error
    with pytest.raises(DeviceNotFound):
        cam.open()
    (tmp_path / "moved").rename(rec)
    cam.open()
    cam.start()
    assert int(cam.grab(1.0).data[0, 0]) == 0
    cam.close()


def test_empty_folder_and_bad_arguments(tmp_path):
    with pytest.raises(DeviceNotFound):
        ReplayCamera(tmp_path).open()
    with pytest.raises(ValueError, match="speed"):
        ReplayCamera(tmp_path, speed=0)
