"""Camera backends report the bit depth of their frames (issue 14)."""

from __future__ import annotations

import numpy as np

from app.capture.captureset import CaptureSet, write_capture_set
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
        assert frame.bit_depth == 12 and frame.data.dtype == np.uint16 and int(frame.data.max()) <= 4095
    finally:
        cam.close()
