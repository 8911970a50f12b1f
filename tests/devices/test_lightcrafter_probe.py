"""``fringescope probe lightcrafter HOST`` (a real CLI process) against the emulator on TCP."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.devices.lightcrafter_emulator import LightCrafterEmulator
from app.recon.patterns import PatternSchedule, generate_patterns

ROOT = Path(__file__).resolve().parents[2]


def _probe(port: int, *extra: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "app", "probe", "lightcrafter", "127.0.0.1", "--port",
           str(port), "--show-s", "0", "--flash-s", "0", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_probe_passes_every_step_and_leaves_the_lights_off():
    with LightCrafterEmulator() as emu:
        proc = _probe(emu.port, "--led-current", "120")
        assert proc.returncode == 0, proc.stdout + proc.stderr
        lines = proc.stdout.splitlines()
        assert [line.split(":")[0] for line in lines[:-1]] == [
            "ok   version", "ok   FPGA and MSP430 versions", "ok   status", "ok   pattern",
            "ok   trigger output", "ok   LEDs"]
        assert lines[0] == "ok   version: DM365 '5.0.0'; sequence command 0x0480"
        assert lines[2] == "ok   status: display mode 0, LED current R/G/B (274, 274, 274)"
        assert lines[-1] == "6/6 steps ok"
        st = emu.state
        schedule = PatternSchedule()
        four_fringes = generate_patterns(schedule)[schedule.frame_index(1, 0)]
        assert np.array_equal(st.patterns[0], np.round(four_fringes * (63 / 255)))  # 6 LSBs
        assert st.sequence["count"] == 1 and st.sequence["bit_depth"] == 6
        assert st.sequence["led"] == 2  # the last LED flashed: blue
        assert st.led_current == (0, 0, 0) and not st.running  # lights off at the end
        assert st.trigger_out["enable"] == 1 and st.trigger_out["width_us"] == 100
        assert st.refusals == []


def test_probe_reports_a_refusal_and_still_turns_the_lights_off():
    with LightCrafterEmulator() as emu:
        emu.fail_next = 0x04
        proc = _probe(emu.port)
        assert proc.returncode == 1
        assert proc.stdout.splitlines()[0] == (
            "FAIL version: LightCrafter refused command 0x0100: "
            "out of memory or hardware failure (0x04)")
        assert proc.stdout.splitlines()[-1] == "0/1 steps ok; failed: version"
        assert emu.state.commands[-2:] == [0x0402, 0x0104] and emu.state.led_current == (0, 0, 0)


def test_probe_goes_on_after_a_refused_read():
    """A firmware that refuses to read the display mode fails that step only."""
    with LightCrafterEmulator() as emu:
        emu.refuse[(0x04, 0x0101)] = 0x02
        proc = _probe(emu.port)
        assert proc.returncode == 1
        lines = proc.stdout.splitlines()
        assert lines[2] == ("FAIL status: LightCrafter refused command 0x0101: "
                            "invalid command (0x02)")
        assert [line[:4] for line in lines[3:-1]] == ["ok  "] * 3
        assert lines[-1] == "5/6 steps ok; failed: status"
        assert emu.state.refusals == [(0x0101, 0x02)] and emu.state.led_current == (0, 0, 0)


def test_probe_bad_input_and_no_projector_exit_2_with_one_line():
    with socket.socket() as s:  # a port with nobody listening
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    proc = _probe(free)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "cannot connect" in proc.stderr
    proc = _probe(free, "--led-current", "500")
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "fringescope probe: error: --led-current: need a code within 0-274, got 500")


@pytest.mark.parametrize(("firmware", "command"), [("2.0.0", "0x0400 (legacy)"),
                                                   ("5.0.0", "0x0480")])
def test_emulate_and_probe_from_the_command_line(firmware, command):
    emu = subprocess.Popen([sys.executable, "-m", "app", "emulate", "lightcrafter", "--port", "0",
                            "--firmware", firmware], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert emu.stdout is not None
        port = int(emu.stdout.readline().strip().rsplit(":", 1)[1])
        proc = _probe(port)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert f"'{firmware}'" in proc.stdout and f"sequence command {command}" in proc.stdout
    finally:
        emu.send_signal(signal.SIGINT)
        assert emu.wait(timeout=30) == 0
