"""Dropped frames, device disconnects and shutdown, each on its own app instance."""

from __future__ import annotations

import socket
import threading
import time
from datetime import datetime
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.helpers.live_app import live_settings, wait_for, wait_result


def _groups_gap_free(frame_indices: list[int], steps: int = 4) -> bool:
    """Each frequency group of a set is ``steps`` consecutive frames (no dropped frame inside)."""
    groups = [frame_indices[g: g + steps] for g in range(0, len(frame_indices), steps)]
    return all(grp == list(range(grp[0], grp[0] + steps)) for grp in groups)


def test_a_dropped_frame_costs_only_its_group(tmp_path: Path, sim_calibration_file: Path) -> None:
    settings = live_settings(tmp_path, sim_calibration_file, sim_drop_rate=0.03)
    with TestClient(create_app(settings)) as client:
        st = wait_for(client, lambda s: s["groups_lost"] >= 3 and s["patched_sets"] >= 1
                      and s["results_published"] >= 3, 120, "lost groups, patched sets and results")
        assert st["frames_dropped"] >= st["groups_lost"] > 0
        # every published result is built of gap-free groups, in pattern order, within 3 cycles
        for _ in range(6):
            meta = wait_result(client, lambda m: True, 10)
            idx = meta["frame_indices"]
            assert _groups_gap_free(idx) and max(idx) - min(idx) < 3 * 16, idx
            time.sleep(0.3)


def test_a_camera_dropping_most_frames_gives_no_depth_and_says_why(
    tmp_path: Path, sim_calibration_file: Path
) -> None:
    # half the frames dropped: a group of 4 survives with p = 1/16, all 4 groups within 3
    # cycles with p = 0.001 a cycle: practically no depth, and the status says why
    settings = live_settings(tmp_path, sim_calibration_file, sim_drop_rate=0.5)
    with TestClient(create_app(settings)) as client:
        st = wait_for(
            client, lambda s: any("dropped" in w for w in s["warnings"]), 60, "the drop warning"
        )
        warning = next(w for w in st["warnings"] if "dropped" in w)
        assert "4 consecutive frames" in warning and st["frames_dropped"] > 0
        assert st["state"] != "running" and st["depth_fps"] == 0
        st = wait_for(client, lambda s: s["state"] == "stalled", 30, "the stalled state")
        reason = st["state_reason"]
        assert "dropped" in reason or "recovering" in reason, reason
        if st["results_published"]:  # a rare set: built of gap-free groups all the same
            assert _groups_gap_free(client.get("/api/result/latest").json()["frame_indices"])


def test_disconnect_shows_a_fault_and_recovers(tmp_path: Path, sim_calibration_file: Path) -> None:
    settings = live_settings(tmp_path, sim_calibration_file, sim_disconnect_every_s=2.0)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda s: s["results_published"] >= 1, 120, "first result")
        st = wait_for(client, lambda s: s["state"] == "fault", 30, "fault state")
        assert st["last_error"] and st["faults"] >= 1
        before = st["results_published"]
        st = wait_for(
            client,
            lambda s: s["state"] == "running" and s["results_published"] > before,
            30,
            "recovery with new results",
        )
        assert st["faults"] >= 1 and st["last_error"]
        # the fault stays on record, with its time, marked resolved by the maps after it
        assert st["last_error_resolved"] is True and st["last_error_at"]
        # both threads survived the faults
        inst = client.app.state.instrument  # type: ignore[attr-defined]
        assert inst.acquisition.alive and inst.pipeline.reconstruction.alive


def test_a_device_fault_not_yet_recorded_is_named_in_the_status(
        tmp_path: Path, sim_calibration_file: Path) -> None:
    """A device in its fault state before the acquisition thread records it (the moment after
    an unplug): a status that says "fault" names the device's error and counts the fault."""
    from app.devices.errors import DeviceDisconnected

    settings = live_settings(tmp_path, sim_calibration_file)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda s: s["results_published"] >= 1, 120, "first result")
        inst = client.app.state.instrument  # type: ignore[attr-defined]
        controller = inst.pipeline.devices.controller
        assert controller is not None and inst.acquisition.fault is None

        def unplugged() -> None:
            raise DeviceDisconnected("link lost (unplugged by the test)")

        with pytest.raises(DeviceDisconnected):
            controller._call("poll", unplugged)  # the base class's own fault path
        st = client.get("/api/status").json()
        assert st["state"] == "fault"
        assert st["last_error"] and "unplugged by the test" in st["last_error"]
        assert st["faults"] >= 1 and st["state_reason"]


@pytest.mark.serial
def test_status_never_says_running_without_a_recent_map(tmp_path: Path,
                                                        sim_calibration_file: Path) -> None:
    """Injected faults (unplugs, drops, timeouts): every status sample that says running has a
    depth map within 2 set periods before it, by the maps' own creation times."""
    from app.devices.sim.world import READOUT_MS

    settings = live_settings(tmp_path, sim_calibration_file, sim_disconnect_every_s=3.0,
                             sim_drop_rate=0.05, sim_timeout_rate=0.02)
    nominal_s = 16 * max(settings.exposure_ms, READOUT_MS) / 1000.0
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda s: s["results_published"] >= 1, 120, "first result")

        def newest_created() -> tuple[int, float] | None:
            r = client.get("/api/result/latest")
            if r.status_code != 200:
                return None
            meta = r.json()
            return meta["seq"], datetime.fromisoformat(meta["created"]).timestamp()

        states: dict[str, int] = {}
        reasons: set[str] = set()
        bad: list[str] = []
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            before = newest_created()
            t_a = time.time()
            st = client.get("/api/status").json()
            t_b = time.time()
            after = newest_created()
            states[st["state"]] = states.get(st["state"], 0) + 1
            if st["state"] != "running":
                reasons.add(f"{st['state']}: {st['state_reason']}")
                assert st["state_reason"], st
            else:
                period = st["set_period_s"]
                assert 0.8 * nominal_s <= period <= 1.5 * nominal_s, (period, nominal_s)
                known = [m[1] for m in (before, after) if m is not None and m[1] <= t_b]
                if not known or t_a - max(known) > 2 * period + 0.05:
                    newest = max(known, default=0.0)
                    bad.append(f"running at {t_a:.3f} with the newest map at {newest:.3f}")
            time.sleep(0.2)
        print(f"\nstatus samples under faults: {states}; reasons seen: {sorted(reasons)[:6]}")
        assert not bad, bad
        assert states.get("running", 0) > 0 and sum(states.values()) - states.get("running", 0) > 0


def test_warm_up_losses_are_counted_apart(tmp_path: Path, sim_calibration_file: Path) -> None:
    settings = live_settings(tmp_path, sim_calibration_file)
    with TestClient(create_app(settings)) as client:
        st = wait_for(client, lambda s: s["results_published"] >= 3, 120, "results")
        warm, since = st["warmup"], st["since_warmup"]
        assert warm and warm["frames_received"] >= 16  # the first map needed a set at least
        for key, total in since.items():
            assert total == st[key] - warm[key] if key in st else total >= 0
        assert st["phase"] is None and st["state_reason"] is None and st["state"] == "running"


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


@pytest.mark.parametrize("viewer", [False, True])
def test_shutdown_joins_every_thread(
    tmp_path: Path, sim_calibration_file: Path, viewer: bool
) -> None:
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
