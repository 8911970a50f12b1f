"""OpenCV camera over a real MJPG video file written with cv2.VideoWriter."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from app.devices import DeviceNotFound, DeviceTimeout
from app.devices.opencv_camera import OpenCVCamera, to_mono
from tests.helpers.videos import H, N, W, frame_level, write_video


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    return write_video(tmp_path_factory.mktemp("video") / "fringes.avi")


def _expected_mono(k: int) -> float:
    return 0.299 * min(255, frame_level(k) + 20) + 0.587 * frame_level(k) + 0.114 * frame_level(k)


def test_file_frames_are_mono_in_order_with_pattern_indices(video):
    cam = OpenCVCamera(str(video), fps=0)
    caps = cam.capabilities
    assert (caps.width, caps.height) == (W, H)
    cam.open()
    cam.start()
    frames = [cam.grab(timeout_s=2.0) for _ in range(N + 3)]
    cam.close()
    for i, f in enumerate(frames):
        assert f.data.shape == (H, W) and f.data.dtype == np.uint8
        assert f.index == i and f.pattern_index == i % N
        assert abs(float(f.data.mean()) - _expected_mono(i % N)) < 3.0  # MJPG is lossy
    assert np.array_equal(frames[N].data, frames[0].data)  # looped back to the first frame


def test_sync_restarts_pattern_counting(video):
    cam = OpenCVCamera(str(video), fps=0, schedule_length=4)
    cam.open()
    cam.start()
    assert [cam.grab(2.0).pattern_index for _ in range(3)] == [0, 1, 2]
    cam.sync()
    assert [cam.grab(2.0).pattern_index for _ in range(5)] == [0, 1, 2, 3, 0]
    cam.close()


@pytest.mark.serial
def test_file_paced_at_requested_rate(video):
    cam = OpenCVCamera(str(video), fps=50.0)
    cam.open()
    cam.start()
    cam.grab(2.0)
    t0 = time.monotonic()
    for _ in range(10):
        cam.grab(2.0)
    elapsed = time.monotonic() - t0
    cam.close()
    assert 0.17 < elapsed < 0.8  # 10 frames at 50 fps = 0.2 s (slack for a loaded machine)


def test_end_of_file_without_loop_times_out(video):
    cam = OpenCVCamera(str(video), fps=0, loop=False)
    cam.open()
    cam.start()
    for _ in range(N):
        cam.grab(2.0)
    with pytest.raises(DeviceTimeout):
        cam.grab(0.3)
    with pytest.raises(DeviceTimeout):
        cam.grab(0.1)
    cam.close()


def test_missing_source_is_not_found(tmp_path):
    with pytest.raises(DeviceNotFound):
        OpenCVCamera(str(tmp_path / "nothing.avi")).open()


def test_to_mono_conversions():
    bgr = np.zeros((2, 3, 3), np.uint8)
    bgr[..., 2] = 100  # red
    assert to_mono(bgr).tolist() == [[30] * 3] * 2
    deep = np.full((2, 2), 4000, np.uint16)
    assert to_mono(deep, 12).dtype == np.uint16 and to_mono(deep, 8).tolist() == [[15, 15]] * 2
    with pytest.raises(ValueError, match="image"):
        to_mono(np.zeros(4, np.uint8))
