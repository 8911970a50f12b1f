"""Dropped frames, device disconnects and shutdown, each on its own app instance."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.api.conftest import live_settings, wait_for, wait_result


def test_sets_with_dropped_frames_are_discarded(tmp_path: Path, sim_calibration_file: Path) -> None:
    settings = live_settings(tmp_path, sim_calibration_file, sim_drop_rate=0.03)
    with TestClient(create_app(settings)) as client:
        st = wait_for(client, lambda s: s["incomplete_sets"] >= 3 and s["results_published"] >= 3, 120,
                      "incomplete sets and results")
        assert st["frames_dropped"] >= st["incomplete_sets"] > 0
        # every published result is one whole, gap-free set
        for _ in range(3):
            meta = wait_result(client, lambda m: True, 10)
            idx = meta["frame_indices"]
            assert idx == list(range(idx[0], idx[0] + 16))
            time.sleep(0.3)


def test_a_camera_dropping_most_frames_gives_no_depth_and_says_why(tmp_path: Path, sim_calibration_file: Path) -> None:
    # half the frames dropped: 16 consecutive ones (p = 2^-16 per set) practically never come
    settings = live_settings(tmp_path, sim_calibration_file, sim_drop_rate=0.5)
    with TestClient(create_app(settings)) as client:
        st = wait_for(client, lambda s: any("dropped" in w for w in s["warnings"]), 60, "the drop warning")
        warning = next(w for w in st["warnings"] if "dropped" in w)
        assert "16 consecutive frames" in warning and st["frames_dropped"] > 0
        assert st["results_published"] == 0  # no depth from frames that are not one gap-free set


def test_disconnect_shows_a_fault_and_recovers(tmp_path: Path, sim_calibration_file: Path) -> None:
    settings = live_settings(tmp_path, sim_calibration_file, sim_disconnect_every_s=2.0)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda s: s["results_published"] >= 1, 120, "first result")
        st = wait_for(client, lambda s: s["state"] == "fault", 30, "fault state")
        assert st["last_error"] and st["faults"] >= 1
        before = st["results_published"]
        st = wait_for(client, lambda s: s["state"] == "running" and s["results_published"] > before, 30,
                      "recovery with new results")
        assert st["faults"] >= 1 and st["last_error"]
        # both threads survived the faults
        inst = client.app.state.instrument  # type: ignore[attr-defined]
        assert inst.acquisition.alive and inst.reconstruction.alive


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


@pytest.mark.parametrize("viewer", [False, True])
def test_shutdown_joins_every_thread(tmp_path: Path, sim_calibration_file: Path, viewer: bool) -> None:
    if viewer:
        pytest.importorskip("app.outputs.viewer")
    before = {t.ident for t in threading.enumerate()}
    settings = live_settings(tmp_path, sim_calibration_file, viewer=viewer)
    app = create_app(settings)
    with TestClient(app) as client:
        wait_for(client, lambda s: s["results_published"] >= 1, 120, "first result")
        inst = app.state.instrument
        own = inst.threads()
        assert all(t.is_alive() for t in own)
        port = app.state.viewer.port if viewer else None
        if viewer:
            assert not _port_free(port)
    assert not any(t.is_alive() for t in own)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        extra = [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
        if not extra:
            break
        time.sleep(0.1)
    assert not extra, f"threads still alive after shutdown: {[t.name for t in extra]}"
    if viewer:
        assert _port_free(port)
