"""The simulated devices through their public interfaces: triggering, LED, pacing, faults."""

from __future__ import annotations

import time

import numpy as np
import pytest

from app.core.schedule import PatternSchedule
from app.devices import DeviceDisconnected, DeviceNotFound, DeviceState, DeviceTimeout
from app.devices.sim import create_sim_devices


def _running(**kw):
    dev = create_sim_devices(
        scene="plane", seed=kw.pop("seed", 0), realtime=kw.pop("realtime", False), **kw
    )
    dev.camera.open()
    dev.projector.open()
    dev.projector.load_schedule(PatternSchedule(), exposure_ms=20.0)
    dev.projector.start()
    dev.camera.start()
    return dev


def test_projector_triggers_camera_and_sets_light():
    dev = _running()
    dev.projector.set_led("red", current=0.3)
    frames = [dev.camera.grab(timeout_s=5.0) for _ in range(18)]
    assert [f.pattern_index for f in frames] == [i % 16 for i in range(18)]
    assert [f.index for f in frames] == list(range(18))
    assert all(f.led == "red" and f.exposure_ms == 20.0 for f in frames)
    assert frames[0].meta["current"] == pytest.approx(0.3)
    # the phase shifts are visible: frames 0 and 2 are in anti-phase on lit pixels
    a, b = frames[0].data.astype(int), frames[2].data.astype(int)
    assert np.corrcoef(a[::4, ::4].ravel(), b[::4, ::4].ravel())[0, 1] < 0.5
    dev.projector.stop()
    f = dev.camera.grab(timeout_s=5.0)
    assert f.pattern_index == -1 and f.data.mean() < a.mean() / 4  # free-running, projector dark
    dev.camera.close()
    dev.projector.close()


def test_frame_period_is_max_of_exposure_and_readout():
    dev = _running(realtime=True)
    dev.camera.configure(exposure_ms=40.0)
    dev.camera.grab(timeout_s=30.0)  # the first frame at new settings builds the pattern means
    dev.camera.stop()
    dev.camera.start()  # restart the frame clock now
    t0 = time.monotonic()
    frames = [dev.camera.grab(timeout_s=5.0) for _ in range(6)]
    elapsed = time.monotonic() - t0
    # Timestamps sit on the frame clock; a consumer that fell behind the ring buffer sees
    # index gaps, never a distorted clock.
    idx = np.array([f.index for f in frames])
    np.testing.assert_allclose(
        np.diff([f.timestamp for f in frames]), 0.040 * np.diff(idx), atol=1e-9
    )
    assert elapsed >= 5 * 0.040 - 0.005
    dev.camera.configure(exposure_ms=5.0)  # readout-limited: 45 frames/s
    dev.camera.grab(timeout_s=30.0)
    frames = [dev.camera.grab(timeout_s=5.0) for _ in range(3)]
    idx = np.array([f.index for f in frames])
    np.testing.assert_allclose(np.diff([f.timestamp for f in frames]), np.diff(idx) / 45, atol=1e-9)
    dev.camera.configure(exposure_ms=100.0)
    dev.camera.grab(timeout_s=30.0)
    dev.camera.stop()
    dev.camera.start()
    with pytest.raises(DeviceTimeout):
        dev.camera.grab(timeout_s=0.001)  # the next 100 ms exposure cannot be ready in 1 ms
    dev.camera.close()


def test_dropped_frames_leave_index_gaps():
    dev = _running(drop_rate=0.25, seed=3)
    frames = [dev.camera.grab(timeout_s=5.0) for _ in range(60)]
    idx = np.array([f.index for f in frames])
    gaps = np.diff(idx) - 1
    assert gaps.min() >= 0 and gaps.sum() > 5
    assert dev.camera.faults.dropped == gaps.sum() + idx[0]
    # each frame still carries the pattern it was lit with
    assert all(f.pattern_index == f.index % 16 for f in frames)
    dev.camera.close()


def test_timeouts_are_raised_and_recoverable():
    dev = _running(timeout_rate=0.3, seed=4)
    ok, timeouts = [], 0
    for _ in range(40):
        try:
            ok.append(dev.camera.grab(timeout_s=0.5))
        except DeviceTimeout:
            timeouts += 1
    assert 3 <= timeouts <= 25 and dev.camera.state is DeviceState.RUNNING
    assert len({f.index for f in ok}) == len(ok)
    dev.camera.close()


def test_periodic_disconnect_faults_and_reconnects():
    dev = create_sim_devices(scene="plane", seed=0, realtime=False, disconnect_every_s=0.2)
    cam = dev.camera
    cam.link.reconnect_delay_s = 0.3
    cam.open()
    cam.start()
    with pytest.raises(DeviceDisconnected):
        for _ in range(10000):
            cam.grab(timeout_s=1.0)
            time.sleep(0.005)
    assert cam.state is DeviceState.FAULT and "unplug" in cam.last_error
    with pytest.raises(DeviceNotFound):
        cam.open()
    time.sleep(0.35)
    cam.open()
    cam.start()
    assert cam.grab(timeout_s=1.0).index == 0
    cam.close()


def test_controller_identify_heartbeat_and_unplug():
    dev = create_sim_devices(scene="plane", realtime=False)
    c = dev.controller
    c.open()
    assert "sim" in c.identify()
    c.arm()
    assert not c.watchdog_expired
    c.link.unplug()
    with pytest.raises(DeviceDisconnected):
        c.heartbeat()
    assert c.state is DeviceState.FAULT
    c.link.replug()
    c.open()
    assert c.state is DeviceState.OPEN
    c.close()


def test_bad_arguments():
    with pytest.raises(ValueError, match="bit_depth"):
        create_sim_devices(bit_depth=10)
    with pytest.raises(ValueError, match="drop_rate"):
        create_sim_devices(drop_rate=1.5)
