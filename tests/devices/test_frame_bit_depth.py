"""Camera backends report the bit depth of their frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.capture.captureset import CaptureSet, write_capture_set
from app.devices.base import significant_bits
from app.devices.opencv_camera import OpenCVCamera
from app.devices.replay import ReplayCamera
from app.devices.sim import create_sim_devices


def test_replay_reports_the_recorded_bit_depth(tmp_path):
    frames = np.random.default_rng(1).integers(0, 4096, (16, 6, 8), dtype=np.uint16)
    write_capture_set(tmp_path / "rec" / "set_0000", CaptureSet(frames, bit_depth=12))
    cam = ReplayCamera(tmp_path / "rec", pace=False)
    cam.open()
    try:
        assert cam.capabilities.bit_depths == (12,)
        cam.start()
        frame = cam.grab(1.0)
        assert frame.bit_depth == 12 and frame.data.dtype == np.uint16
    finally:
        cam.close()


def test_simulated_camera_reports_its_bit_depth():
    devs = create_sim_devices(scene="dof_target", seed=1, bit_depth=12)
    cam = devs.camera
    try:
        cam.open()
        cam.start()
        frame = cam.grab(5.0)
        assert (
            frame.bit_depth == 12
            and frame.data.dtype == np.uint16
            and int(frame.data.max()) <= 4095
        )
    finally:
        cam.close()


def test_one_full_scale_rule_for_the_counting_cameras():
    """uint8 frames fill 8 bits; a 16-bit sample fills what its source says (Mono12: 12)."""
    assert significant_bits(np.zeros((2, 2), np.uint8), 16) == 8
    assert significant_bits(np.zeros((2, 2), np.uint16), 12) == 12
    assert significant_bits(np.zeros((2, 2), np.uint16), 16) == 16
    with pytest.raises(ValueError, match="source_bits"):
        significant_bits(np.zeros((2, 2), np.uint16), 8)


def test_opencv_camera_frames_follow_the_rule(tmp_path):
    """A real video file through OpenCV: 8-bit frames say 8, counted against the schedule."""
    path = tmp_path / "fringes.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (32, 24))
    for k in range(6):
        writer.write(np.full((24, 32, 3), 40 * k, np.uint8))
    writer.release()
    cam = OpenCVCamera(str(path), schedule_length=4, fps=0)
    cam.open()
    try:
        cam.start()
        frames = [cam.grab(2.0) for _ in range(5)]
    finally:
        cam.close()
    assert [f.bit_depth for f in frames] == [8] * 5 and frames[0].data.dtype == np.uint8
    assert [f.pattern_index for f in frames] == [0, 1, 2, 3, 0]
    assert [f.index for f in frames] == list(range(5))
