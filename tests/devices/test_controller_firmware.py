"""The REAL firmware source (hardware/firmware/…/fringescope_controller.ino), built for the host
with a small Arduino shim, on a pty: same replies as the Python emulator, and the driver works with
it."""

from __future__ import annotations

import os
import re
import select
import shutil
import subprocess
import time
import tty
from pathlib import Path

import pytest
import serial

from app.devices import DeviceState
from app.devices.controller_emulator import ControllerProtocol
from app.devices.serial_controller import ControllerError, SerialController
from tests.helpers.protocol_doc import protocol_table

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE_DIR = ROOT / "hardware" / "firmware"

pytestmark = pytest.mark.skipif(shutil.which("g++") is None or shutil.which("make") is None,
                                reason="needs g++ and make to build the firmware for the host")


@pytest.fixture(scope="module")
def firmware_binary(tmp_path_factory) -> Path:
    build = tmp_path_factory.mktemp("fw")
    subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE_DIR), "host", f"BUILD={build}"], check=True, timeout=120
    )
    return build / "fringescope_controller_host"


class FirmwareOnPty:
    """The firmware process owns the master end; ``port`` is the slave device to open."""

    def __init__(self, binary: Path, interlock_file: Path) -> None:
        master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        env = {**os.environ, "FIRMWARE_INTERLOCK_FILE": str(interlock_file)}
        self.proc = subprocess.Popen([str(binary)], stdin=master, stdout=master, env=env)
        os.close(master)
        self._await_banner()

    def _await_banner(self, timeout_s: float = 10.0) -> None:
        # the boot banner comes when the process has started, which a loaded host delays:
        # consume it here, as the driver does, so every test starts at a quiet prompt
        seen = b""
        deadline = time.monotonic() + timeout_s
        while b"ready" not in seen:
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"firmware printed no boot banner in {timeout_s} s (got {seen!r})"
                )
            readable, _, _ = select.select([self._slave], [], [], 0.1)
            if readable:
                seen += os.read(self._slave, 256)
        while select.select([self._slave], [], [], 0.05)[0]:  # the rest of the banner line
            os.read(self._slave, 256)

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(timeout=5)
        os.close(self._slave)


@pytest.fixture
def firmware(firmware_binary, tmp_path):
    fw = FirmwareOnPty(firmware_binary, tmp_path / "interlock_open")
    yield fw
    fw.close()


SCRIPT = [
    "*IDN?", "VER?", "LED?", "CUR G 500", "CUR? G", "LED G", "LED?", "LED X", "CUR G", "CUR B 1001",
    "CUR Q 5", "TMODE PASS", "TMODE FAST", "TPER 999", "TPER 25000", "TDLY 100001", "TDLY 500",
    "TWID 9", "TWID 200", "TCNT 65536", "TCNT 16", "WDT 99", "WDT 1500", "WDT?", "HB", "HB 1",
    "ARM", "TPER 5000", "DISARM", "STAT?", "NOPE", "X" * 70, "*RST", "STAT?", "LED OFF", "LED?",
]


def _boundary_lines() -> list[str]:
    """Each documented numeric range at lo-1, lo, hi, hi+1 (from hardware/PROTOCOL.md)."""
    lines = []
    for cmd, _args, rng, _example, _reply in protocol_table("Commands"):
        m = re.search(r"(\d+)–(\d+)", rng)
        if m:
            prefix = "CUR B " if cmd == "`CUR`" else cmd.strip("`") + " "
            lo, hi = int(m.group(1)), int(m.group(2))
            lines += [f"{prefix}{v}" for v in (lo - 1, lo, hi, hi + 1) if v >= 0]
    return lines


def test_firmware_and_emulator_reply_identically(firmware):
    proto = ControllerProtocol(serial="FS0001")
    script = SCRIPT + _boundary_lines()
    assert len(script) > len(SCRIPT) + 20
    with serial.serial_for_url(firmware.port, baudrate=115200, timeout=2.0) as port:
        for line in script:
            port.write(line.encode() + b"\n")
            got = port.readline().decode().strip()
            want = proto.handle_line(line)
            if line == "*IDN?":
                # firmware versions differ
                got, want = got.rsplit(",", 1)[0], want.rsplit(",", 1)[0]
            if line == "STAT?":  # pulse count depends on timing; TMODE PASS gets none
                got, want = got.rsplit(" pulses=", 1)[0], want.rsplit(" pulses=", 1)[0]
            if want.startswith("ERR"):  # messages are for humans: compare the codes
                got, want = got.split()[:2], want.split()[:2]
            assert got == want, line


def test_firmware_counts_internal_trigger_pulses(firmware):
    with serial.serial_for_url(firmware.port, baudrate=115200, timeout=2.0) as port:
        for line in (b"TPER 2000", b"TCNT 16", b"ARM"):
            port.write(line + b"\n")
            assert port.readline().strip() == b"OK"
        counts = []
        deadline = time.monotonic() + 5.0  # 16 pulses need 30 ms; a loaded host runs the loop late
        while not counts or (counts[-1] < 16 and time.monotonic() < deadline):
            time.sleep(0.05)
            port.write(b"STAT?\n")
            counts.append(int(port.readline().strip().rsplit(b"pulses=", 1)[1]))
        time.sleep(0.1)
        port.write(b"STAT?\n")
        counts.append(int(port.readline().strip().rsplit(b"pulses=", 1)[1]))
        assert counts[-2:] == [16, 16] and counts == sorted(counts)  # counts up to TCNT and stops


def test_driver_runs_the_real_firmware_and_its_safety(firmware, tmp_path):
    ctl = SerialController(firmware.port, reset_wait_s=0.05, watchdog_ms=300, timeout_s=1.0)
    ctl.open()
    try:
        assert ctl.identify().startswith("FRINGESCOPE,LEDCTRL,FS0001,")
        ctl.set_led("blue", current=0.3)
        ctl.arm()
        time.sleep(1.0)  # > 3 watchdog periods: the heartbeat thread keeps it alive
        st = ctl.status()
        assert (
            st["led"] == "B"
            and st["cur"] == "0/500/300"
            and st["armed"] == "1"
            and st["wdt"] == "ok"
        )
        (tmp_path / "interlock_open").touch()
        time.sleep(0.05)
        st = ctl.status()
        assert st["intlk"] == "open" and st["led"] == "OFF" and st["armed"] == "0"
        with pytest.raises(ControllerError) as info:
            ctl.arm()
        assert info.value.code == 4 and ctl.state is not DeviceState.FAULT
        (tmp_path / "interlock_open").unlink()
        time.sleep(0.05)  # the firmware polls the input once per loop
        ctl.set_led("green", current=0.5)
    finally:
        ctl.close()
    with serial.serial_for_url(firmware.port, baudrate=115200, timeout=2.0) as port:
        port.write(b"STAT?\n")
        reply = port.readline()
        while reply.startswith(b"#"):
            reply = port.readline()
    assert b"led=OFF" in reply and b"armed=0" in reply  # the driver switched lights off on close


def test_firmware_watchdog_trips_without_heartbeats(firmware):
    with serial.serial_for_url(firmware.port, baudrate=115200, timeout=2.0) as port:
        for line in (b"WDT 200", b"LED R", b"ARM"):
            port.write(line + b"\n")
            assert port.readline().strip() == b"OK"
        assert port.readline().strip() == b"# WATCHDOG tripped"  # arrives after ~200 ms
        port.write(b"ARM\n")
        assert port.readline().startswith(b"ERR 5")
        port.write(b"STAT?\n")
        assert b"led=OFF" in port.readline()
