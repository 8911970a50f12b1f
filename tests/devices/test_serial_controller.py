"""Serial LED/trigger controller: protocol document ↔ emulator ↔ firmware, and the driver over a
real pty."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
import serial
from serial.tools.list_ports_common import ListPortInfo

from app.devices import DeviceError, DeviceNotFound, DeviceState, DeviceTimeout, ProtocolError
from app.devices.controller_emulator import ControllerProtocol, PtyControllerEmulator
from app.devices.serial_controller import ControllerError, SerialController, resolve_port
from tests.helpers.protocol_doc import ROOT, protocol_table

FIRMWARE = ROOT / "hardware" / "firmware" / "fringescope_controller" / "fringescope_controller.ino"

def _wait_until(pred, timeout_s: float = 2.0) -> float:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError("condition not reached in time")
        time.sleep(0.01)
    return time.monotonic() - t0


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


# --- the protocol document, the emulator and the firmware agree --------------------------------
def test_every_documented_command_example_is_accepted_by_the_emulator():
    """The examples, run in table order on one device, give the documented replies."""
    rows = protocol_table("Commands")
    assert len(rows) >= 15
    proto = ControllerProtocol()
    for cmd, _args, _range, example, reply in rows:
        line = example.strip("`")
        assert line.split()[0] == cmd.strip("`")
        out = proto.handle_line(line)
        assert out.startswith("OK"), f"{line!r} -> {out!r}"
        documented = reply.split("`")[1]
        if cmd == "`STAT?`":  # same fields in the same order
            assert [f.split("=")[0] for f in out.split()] == [
                f.split("=")[0] for f in documented.split()
            ]
        elif "<" not in documented:
            assert out == documented, f"{line!r} -> {out!r}, documented {documented!r}"


def test_documented_numeric_ranges_are_enforced():
    checked = 0
    for cmd, _args, rng, _example, _reply in protocol_table("Commands"):
        m = re.search(r"(\d+)–(\d+)", rng)
        if not m:
            continue
        name, lo, hi = cmd.strip("`"), int(m.group(1)), int(m.group(2))
        prefix = f"{name} G " if name == "CUR" else f"{name} "
        p = ControllerProtocol()
        assert p.handle_line(f"{prefix}{lo}") == "OK" and p.handle_line(f"{prefix}{hi}") == "OK"
        assert p.handle_line(f"{prefix}{hi + 1}").startswith("ERR 3")
        if lo > 0:
            assert p.handle_line(f"{prefix}{lo - 1}").startswith("ERR 3")
        checked += 1
    assert checked == 6  # CUR TPER TDLY TWID TCNT WDT


def test_every_documented_command_is_in_the_firmware():
    source = FIRMWARE.read_text(encoding="utf-8")
    for row in protocol_table("Commands"):
        assert f'"{row[0].strip("`")}"' in source, row[0]
    for code, name, _ in protocol_table("Error codes"):
        assert f"err({code}," in source, name


def test_every_documented_error_code_is_produced():
    codes = {int(row[0]) for row in protocol_table("Error codes")}
    clock = Clock()
    p = ControllerProtocol(clock=clock)
    seen = {
        p.handle_line("FOO"), p.handle_line("CUR G"), p.handle_line("CUR G 1001"),
        p.handle_line("X" * 64),
    }
    p.set_interlock(True)
    seen.add(p.handle_line("LED G"))
    p.set_interlock(False)
    p.handle_line("LED G")
    clock.t += 3.0  # past the 2 s default watchdog
    p.tick()
    seen.add(p.handle_line("ARM"))
    p.handle_line("LED G")
    p.handle_line("ARM")
    seen.add(p.handle_line("TPER 5000"))
    produced = {int(s.split()[1]) for s in seen if s.startswith("ERR")}
    assert produced == codes


def test_watchdog_and_interlock_switch_lights_off():
    clock = Clock()
    p = ControllerProtocol(clock=clock)
    assert p.handle_line("WDT 500") == "OK"
    assert p.handle_line("CUR B 300") == "OK" and p.handle_line("LED B") == "OK"
    assert p.handle_line("ARM") == "OK"
    clock.t += 0.4
    assert p.handle_line("HB") == "OK"  # restarts the timer
    clock.t += 0.4
    p.tick()
    assert p.led == "B" and p.armed
    clock.t += 0.2
    p.tick()
    assert p.led == "OFF" and not p.armed and p.tripped
    assert p.notices == ["# WATCHDOG tripped"]
    assert p.handle_line("ARM").startswith("ERR 5")
    assert p.handle_line("LED B") == "OK" and p.handle_line("ARM") == "OK"
    p.set_interlock(True)
    assert p.led == "OFF" and not p.armed
    assert "intlk=open" in p.handle_line("STAT?")


def test_internal_trigger_counts_pulses_up_to_tcnt():
    clock = Clock()
    p = ControllerProtocol(clock=clock)
    for line in ("TPER 10000", "TCNT 16", "LED G", "ARM"):
        assert p.handle_line(line) == "OK"
    clock.t += 0.0555  # pulses at 0, 10, 20, 30, 40, 50 ms
    assert "pulses=6" in p.handle_line("STAT?")
    clock.t += 1.0
    assert "pulses=16" in p.handle_line("STAT?")


# --- the driver over a real pty ----------------------------------------------------------------
@pytest.fixture
def emu(tmp_path):
    e = PtyControllerEmulator(tmp_path / "ttyFRINGE").start()
    yield e
    e.stop()


def _ctl(port: str, **kw) -> SerialController:
    kw.setdefault("reset_wait_s", 0.02)
    kw.setdefault("watchdog_ms", 400)
    kw.setdefault("timeout_s", 0.3)
    return SerialController(port, **kw)


def test_open_identify_led_arm_over_pty(emu):
    ctl = _ctl(emu.port)
    ctl.open()
    try:
        assert ctl.identify().startswith("FRINGESCOPE,LEDCTRL,EMU0001,")
        ctl.set_led("blue", current=0.25)
        assert emu.protocol.led == "B" and emu.protocol.currents["B"] == 250
        ctl.arm()
        time.sleep(0.1)
        st = ctl.status()
        assert st["armed"] == "1" and st["led"] == "B" and st["mode"] == "INT"
        assert 1 <= int(st["pulses"]) <= 16
        emu.protocol.set_interlock(True)
        with pytest.raises(ControllerError) as info:
            ctl.arm()
        assert info.value.code == 4 and isinstance(info.value, ProtocolError)
        assert ctl.state is not DeviceState.FAULT  # a refusal is not a lost link
    finally:
        ctl.close()
    assert emu.protocol.led == "OFF" and not emu.protocol.armed  # lights off on close


def test_heartbeat_thread_keeps_the_watchdog_fed(emu):
    ctl = _ctl(emu.port, watchdog_ms=300)
    ctl.open()
    ctl.set_led("green", current=0.5)
    time.sleep(1.0)  # > 3 watchdog periods
    assert emu.protocol.led == "G" and not emu.protocol.tripped
    ctl.close()


def test_without_heartbeats_the_device_watchdog_trips(emu):
    with serial.serial_for_url(emu.port, baudrate=115200, timeout=0.5) as port:
        for line in (b"WDT 200\n", b"LED G\n"):
            port.write(line)
            assert port.readline().startswith(b"OK")
        time.sleep(0.4)
        port.reset_input_buffer()
        port.write(b"STAT?\n")
        reply = port.readline()
    assert b"led=OFF" in reply and b"wdt=tripped" in reply


def test_port_is_exclusive(emu):
    first = _ctl(emu.port)
    first.open()
    try:
        with pytest.raises(DeviceError, match="busy"):
            _ctl(emu.port).open()
    finally:
        first.close()


def test_missing_port_and_wrong_device():
    with pytest.raises(DeviceNotFound):
        _ctl("/dev/does-not-exist-fringe").open()
    with PtyControllerEmulator(protocol=ControllerProtocol(version="2.0")) as e, \
            pytest.raises(ProtocolError, match="protocol 2.0"):
        _ctl(e.port).open()


def test_dropped_reply_is_a_timeout_and_late_replies_do_not_leak(emu):
    ctl = _ctl(emu.port, auto_reconnect=False)
    ctl.open()
    try:
        emu.reply_delay_s = 0.5  # later than the 0.3 s timeout
        with pytest.raises(DeviceTimeout):
            ctl.identify()
        emu.reply_delay_s = 0.0
        time.sleep(0.6)  # the late "OK" to the earlier command is now in the buffer
        assert ctl.identify().startswith("FRINGESCOPE")
        assert ctl.state is DeviceState.OPEN
    finally:
        ctl.close()


def test_silent_device_faults_then_recovers(emu):
    ctl = _ctl(emu.port, watchdog_ms=400)
    ctl.open()
    try:
        emu.drop_rate = 1.0
        _wait_until(lambda: ctl.state is DeviceState.FAULT, 3.0)
        assert "no reply to 3 heartbeats" in ctl.last_error
        emu.drop_rate = 0.0
        assert _wait_until(lambda: ctl.state is DeviceState.OPEN, 2.0) < 2.0
    finally:
        ctl.close()


@pytest.mark.serial
def test_unplug_faults_and_replug_resumes_within_2_s(emu):
    ctl = _ctl(emu.port)
    ctl.open()
    ctl.set_led("red", current=0.6)
    ctl.arm()
    first_device = emu.slave_name
    emu.vanish()
    _wait_until(lambda: ctl.state is DeviceState.FAULT, 2.0)
    assert "link lost" in ctl.last_error
    time.sleep(0.3)  # stays down meanwhile, retrying
    assert ctl.state is DeviceState.FAULT
    emu.reappear()
    assert emu.slave_name != first_device or os.path.exists(first_device)
    took = _wait_until(lambda: ctl.state is DeviceState.RUNNING, 2.0)
    assert took < 2.0 and ctl.reconnects == 1
    assert emu.protocol.led == "R" and emu.protocol.currents["R"] == 600 and emu.protocol.armed
    ctl.close()


@pytest.mark.serial
def test_reboot_on_open_the_banner_ends_the_reset_wait(tmp_path):
    """Arduino-like board: deaf for 0.3 s after each open, then the banner."""
    emu = PtyControllerEmulator(tmp_path / "ttyUNO", auto_reset_s=0.3).start()
    try:
        with pytest.raises(DeviceTimeout):  # talking at once: the booting board loses the bytes
            _ctl(emu.port, reset_wait_s=0.0).open()
        time.sleep(0.5)  # let the emulator see the port closed (it polls for the hang-up)
        ctl = _ctl(emu.port, reset_wait_s=2.0)
        t0 = time.monotonic()
        ctl.open()
        took = time.monotonic() - t0
        assert 0.3 <= took < 1.5  # waited for the boot, not the full 2 s
        ctl.set_led("green")
        ctl.arm()
        emu.vanish()
        _wait_until(lambda: ctl.state is DeviceState.FAULT, 2.0)
        emu.reappear()
        assert _wait_until(lambda: ctl.state is DeviceState.RUNNING, 2.0) < 2.0
        assert emu.protocol.armed and emu.protocol.led == "G"
        ctl.close()
    finally:
        emu.stop()


def test_usb_identity_finds_the_port_again_after_replug():
    emu = PtyControllerEmulator().start()  # no symlink: the device name changes on replug

    def ports():
        info = ListPortInfo(emu.slave_name, skip_link_detection=True)
        info.vid, info.pid, info.serial_number = 0x2341, 0x0043, "FS0001"
        other = ListPortInfo("/dev/ttyUSB9", skip_link_detection=True)
        other.vid, other.pid, other.serial_number = 0x0403, 0x6001, "X"
        return [other, info] if emu.present else [other]

    ctl = _ctl("usb:2341:0043:FS0001", list_ports_fn=ports)
    try:
        ctl.open()
        emu.vanish()
        _wait_until(lambda: ctl.state is DeviceState.FAULT, 2.0)
        emu.reappear()
        _wait_until(lambda: ctl.state is DeviceState.OPEN, 2.0)
        assert ctl.identify().startswith("FRINGESCOPE")
    finally:
        ctl.close()
        emu.stop()


def test_resolve_port_spellings():
    a = ListPortInfo("/dev/ttyACM0", skip_link_detection=True)
    a.vid, a.pid, a.serial_number = 0x2341, 0x0043, "A1"
    b = ListPortInfo("/dev/ttyACM1", skip_link_detection=True)
    b.vid, b.pid, b.serial_number = 0x2341, 0x0043, "B2"
    assert resolve_port("/dev/ttyS0", []) == "/dev/ttyS0"
    assert resolve_port("loop://", []) == "loop://"
    assert resolve_port("usb:2341:0043:B2", [a, b]) == "/dev/ttyACM1"
    with pytest.raises(DeviceNotFound, match="several"):
        resolve_port("usb:2341:0043", [a, b])
    with pytest.raises(DeviceNotFound):
        resolve_port("usb:1234:5678", [a, b])
    with pytest.raises(ValueError, match="port"):
        resolve_port("usb:zz:0043", [])
    with pytest.raises(ValueError, match="port"):
        SerialController("usb:2341")


def test_cli_emulate_controller_prints_a_working_device(tmp_path):
    link = tmp_path / "ttyCLI"
    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "emulate", "controller", "--link", str(link)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        assert path == str(link)
        ctl = _ctl(path)
        ctl.open()
        assert ctl.identify().startswith("FRINGESCOPE,LEDCTRL")
        ctl.close()
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    assert not link.exists()
