"""``fringescope serve`` as a real process: flags reach the settings, the API answers, Ctrl-C
stops it."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from tests.helpers.served import ServedApp, free_port


def test_serve_starts_answers_and_stops(tmp_path: Path, sim_calibration_file: Path) -> None:
    port = free_port()
    config = tmp_path / "fringescope.toml"
    config.write_text(
        "[fringescope]\nexposure_ms = 42.0\nautostart = false\nviewer = false\n",
        encoding="utf-8",
    )
    env = dict(os.environ, FRINGESCOPE_CALIBRATION_FILE=str(sim_calibration_file),
               NUMBA_THREADING_LAYER="workqueue")
    server = ServedApp(["--port", str(port), "--config", str(config),
                        "--data-dir", str(tmp_path / "data")], env, tmp_path / "server.log")
    try:
        deadline = time.monotonic() + 120
        status = None
        while time.monotonic() < deadline and server.running():
            try:
                status = httpx.get(f"http://127.0.0.1:{port}/api/status", timeout=2).json()
                break
            except httpx.HTTPError:
                time.sleep(0.3)
        assert status is not None, server.log() if not server.running() else "no answer"
        assert status["exposure_ms"] == 42.0  # from the config file
        assert status["state"] == "stopped" and status["calibration"]["name"] == "sim"
    finally:
        returncode = server.stop()
    assert returncode == 0, server.log()


def test_serve_bad_config_is_one_line_and_exit_2(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "app", "serve", "--config", str(tmp_path / "missing.toml")],
        capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 2
    assert "config file not found" in r.stderr and "Traceback" not in r.stderr


def test_serve_with_the_igtl_port_taken_is_one_line_and_exit_2(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = int(taken.getsockname()[1])
        env = dict(os.environ, FRINGESCOPE_IGTL_PORT=str(port), FRINGESCOPE_VIEWER="false",
                   NUMBA_THREADING_LAYER="workqueue")
        r = subprocess.run([sys.executable, "-m", "app", "serve", "--port", str(free_port()),
                            "--data-dir", str(tmp_path / "data")],
                           capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2, r.stderr
    assert f"OpenIGTLink port {port} on 127.0.0.1 is not available" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
