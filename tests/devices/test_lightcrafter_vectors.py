"""Byte vectors from TI's DLPU007A field tables, checked against the client AND the emulator.

Every expected packet below is written out by hand from the guide's tables (packet
layout §2, the command tables, the error-code table); no expected byte is computed with
the client's helpers. The client's packets are read back from the emulator's packet log
(what really crossed the TCP socket); the emulator gets the same bytes raw and must
answer as the guide says. The last tests send the three old defects' packets (raw, or a
pattern upload carried by the client's framing) and expect the device's error codes.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.schedule import schedule_by_name
from app.devices.lightcrafter import (
    LightCrafterClient,
    LightCrafterError,
    LightCrafterProjector,
    encode_bmp,
    pack_led_current,
    pack_sequence,
    pack_trigger_out,
)
from app.devices.lightcrafter_emulator import LightCrafterEmulator
from app.recon.patterns import PatternSchedule, generate_patterns
from tests.helpers.lightcrafter import raw_exchange

H = bytes.fromhex
# type 04 read, cmd 01 00, flags 00, length 0001, payload 00 (DM365 software), checksum 06
VERSION_READ = H("04 0100 00 0100 00 06")
# 0x0402 start/stop, 1 byte: 0 stop, 1 start
STOP = H("02 0402 00 0100 00 09")
START = H("02 0402 00 0100 01 0A")
# 0x0101 display mode, 1 byte: 4 pattern sequence
MODE_SEQUENCE = H("02 0101 00 0100 04 09")
# 0x0104 LED current, 3 × uint16 LE (red, green, blue): green 137 (0.5 of the 274 limit)
LED_GREEN_137 = H("02 0104 00 0600 0000 8900 0000 96")
LED_OFF = H("02 0104 00 0600 0000 0000 0000 0D")
# 0x0480 extended sequence, 19 bytes: bit depth 6, count uint16 16, inverted 0, trigger 1
# (auto), delay 0 µs, period 27000 µs, exposure 25000 µs, LED 1 (green), play 1 (continuous)
SEQ_EXT_6BIT_25MS = H("02 0480 00 1300 06 1000 00 01 00000000 78690000 A8610000 01 01 9C")
# the same at 40 ms exposure (period 42000 µs)
SEQ_EXT_6BIT_40MS = H("02 0480 00 1300 06 1000 00 01 00000000 10A40000 409C0000 01 01 42")
# 9 patterns (geometric-9) at 8 bits, 25 ms
SEQ_EXT_8BIT_25MS = H("02 0480 00 1300 08 0900 00 01 00000000 78690000 A8610000 01 01 97")
# 0x0400 legacy sequence, 17 bytes: count one byte, no play mode
SEQ_LEGACY_6BIT_25MS = H("02 0400 00 1100 06 10 00 01 00000000 78690000 A8610000 01 19")
# 0x0404 trigger output, 11 bytes: enable 1, source 0, polarity 0 (positive), delay 0 µs,
# pulse width 100 µs
TRIGGER_OUT = H("02 0404 00 0B00 01 00 00 00000000 64000000 7A")
# 0x0401 pattern definition of pattern 0: an 8-bit BMP of 608 × 684 (1078-byte header and
# palette + 415872 pixel bytes = 416950 = 0x065CB6) after the pattern byte: 416951 bytes,
# sent as 6 parts of 65535 (flags 01 first, 02 middle) and a last part (03) of 23741 = 0x5CBD
PATTERN0_FIRST_PART = H("02 0401 01 FFFF 00 424D B65C0600 00000000 36040000")
PATTERN_PART_HEADS = [H("02 0401 01 FFFF")] + [H("02 0401 02 FFFF")] * 5 + [H("02 0401 03 BD5C")]


@pytest.fixture
def emu():
    e = LightCrafterEmulator().start()
    yield e
    e.stop()



def _sent(emu: LightCrafterEmulator, since: int) -> list[bytes]:
    return list(emu.state.packets)[since:]


def test_packers_follow_the_guide_tables():
    assert pack_led_current(0, 137, 0) == LED_GREEN_137[6:-1]
    assert pack_sequence(bit_depth=6, count=16, trigger=1, delay_us=0, period_us=27000,
                         exposure_us=25000, led=1) == SEQ_EXT_6BIT_25MS[6:-1]
    assert pack_sequence(bit_depth=6, count=16, trigger=1, delay_us=0, period_us=27000,
                         exposure_us=25000, led=1, extended=False) == SEQ_LEGACY_6BIT_25MS[6:-1]
    assert pack_trigger_out(enable=True, delay_us=0, width_us=100) == TRIGGER_OUT[6:-1]
    with pytest.raises(ValueError, match="green"):
        pack_led_current(0, 1025, 0)
    with pytest.raises(ValueError, match="count"):
        pack_sequence(bit_depth=1, count=97, trigger=1, delay_us=0, period_us=1, exposure_us=1,
                      led=1, extended=False)


def test_open_start_stop_close_send_the_guide_packets(emu):
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    assert _sent(emu, 0) == [VERSION_READ, STOP, MODE_SEQUENCE, LED_GREEN_137]
    assert proj.extended_sequence and emu.state.led_current == (0, 137, 0)
    proj.load_schedule(PatternSchedule(), exposure_ms=25.0)
    n = len(emu.state.packets)
    proj.start()
    proj.stop()
    assert _sent(emu, n) == [START, STOP]
    proj.start()
    n = len(emu.state.packets)
    proj.close()
    assert _sent(emu, n) == [STOP, LED_OFF]
    assert emu.state.refusals == []


def test_schedule_load_16_patterns_6_bit_in_the_least_significant_bits(emu):
    schedule = PatternSchedule()
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    n = len(emu.state.packets)
    proj.load_schedule(schedule, exposure_ms=25.0)
    sent = _sent(emu, n)
    assert sent[:2] == [STOP, SEQ_EXT_6BIT_25MS]
    assert sent[-1] == TRIGGER_OUT
    parts = sent[2:-1]
    assert len(parts) == 16 * 7
    assert parts[0][:21] == PATTERN0_FIRST_PART
    for i in range(16):
        assert [p[:6] for p in parts[7 * i:7 * i + 7]] == PATTERN_PART_HEADS
        assert parts[7 * i][6] == i  # the pattern number leads the first part only
    # §3.11: the device shows the 6 least significant bits, so levels 0–63 go up
    expected = np.round(generate_patterns(schedule).astype(np.float64) * 63 / 255)
    assert all(np.array_equal(emu.state.patterns[i], expected[i]) for i in range(16))
    assert max(int(p.max()) for p in emu.state.patterns.values()) == 63
    assert emu.state.refusals == []
    proj.close()


def test_schedule_load_8_bit(emu):
    schedule = schedule_by_name("geometric-9")
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    n = len(emu.state.packets)
    proj.load_schedule(schedule, exposure_ms=25.0)
    sent = _sent(emu, n)
    assert sent[:2] == [STOP, SEQ_EXT_8BIT_25MS] and sent[-1] == TRIGGER_OUT
    expected = generate_patterns(schedule)
    assert all(np.array_equal(emu.state.patterns[i], expected[i]) for i in range(9))
    proj.close()


def test_exposure_change_sends_stop_sequence_start(emu):
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    proj.load_schedule(PatternSchedule(), exposure_ms=25.0)
    proj.start()
    n = len(emu.state.packets)
    proj.set_exposure(40.0)
    assert _sent(emu, n) == [STOP, SEQ_EXT_6BIT_40MS, START]
    proj.close()


def test_legacy_firmware_gets_the_legacy_sequence_command():
    with LightCrafterEmulator(firmware="2.0.0") as emu:
        assert raw_exchange(emu, SEQ_EXT_6BIT_25MS) == H("01 0480 00 0100 02 88")  # invalid command
        proj = LightCrafterProjector(emu.host, emu.port)
        proj.open()
        assert not proj.extended_sequence
        n = len(emu.state.packets)
        proj.load_schedule(PatternSchedule(), exposure_ms=25.0)
        assert _sent(emu, n)[:2] == [STOP, SEQ_LEGACY_6BIT_25MS]
        proj.start()
        assert emu.state.running and emu.state.sequence_command == 0x0400
        proj.close()


@pytest.mark.parametrize(("packet", "reply"), [
    (VERSION_READ, None),
    (MODE_SEQUENCE, H("03 0101 00 0000 05")),
    (LED_GREEN_137, H("03 0104 00 0000 08")),
    (SEQ_EXT_6BIT_25MS, H("03 0480 00 0000 87")),
    (SEQ_LEGACY_6BIT_25MS, H("03 0400 00 0000 07")),
    (TRIGGER_OUT, H("03 0404 00 0000 0B")),
    (STOP, H("03 0402 00 0000 09")),
    (H("02 0103 00 0100 0D 14"), H("03 0103 00 0000 07")),  # last internal test pattern
])
def test_emulator_accepts_the_guide_packets(emu, packet, reply):
    got = raw_exchange(emu, packet)
    if reply is None:  # the version string: read response, its own checksum
        assert got[:3] == H("05 0100") and got[6:-1] == b"5.0.0\0"
        assert got[-1] == sum(got[:-1]) % 256
    else:
        assert got == reply


@pytest.mark.parametrize(("packet", "reply"), [
    (VERSION_READ[:-1] + b"\x07", H("01 0100 00 0100 08 0B")),  # checksum error
    (H("02 0103 00 0100 0E 15"), H("01 0103 00 0100 03 09")),  # test pattern 0x0E: parameter
    (H("02 0104 00 0600 0104 0000 0000 12"), H("01 0104 00 0100 03 0A")),  # 1025 > 1024
    # 0x0480 with trigger type 7 (the table stops at 6): invalid parameter
    (H("02 0480 00 1300 06 1000 00 07 00000000 78690000 A8610000 01 01 A2"),
     H("01 0480 00 0100 03 89")),
    (H("02 0401 02 0800 0000000000000000 11"), H("01 0401 00 0100 0A 11")),  # middle, no first
    (H("00 0000 00 0000 00"), H("01 0000 00 0100 02 04")),  # busy is a device type; no command
])
def test_emulator_refuses_with_the_guide_error_codes(emu, packet, reply):
    assert raw_exchange(emu, packet) == reply


def test_old_led_current_packet_is_refused():
    """LED current sent as 0x0103 (one-byte test pattern) with 6 bytes: payload size error."""
    with LightCrafterEmulator() as emu:
        assert raw_exchange(emu, H("02 0103 00 0600 0000 0002 0000 0E")) == H(
            "01 0103 00 0100 09 0F"
        )
        assert emu.state.led_current == (274, 274, 274)


def test_old_trigger_output_packet_is_refused():
    """10-byte 0x0404 (no trigger-source byte): payload size error, nothing set."""
    with LightCrafterEmulator() as emu:
        assert raw_exchange(emu, H("02 0404 00 0A00 01 00 00000000 64000000 79")) == H(
            "01 0404 00 0100 09 13")
        assert emu.state.trigger_out == {}


def test_old_top_bits_patterns_are_refused_and_would_wrap():
    """A 6-bit pattern uploaded in the top bits (levels 0–252) is refused (0x03); a device
    that takes it shows the low 6 bits, wrong for most pixels."""
    schedule = PatternSchedule()
    full = generate_patterns(schedule)
    old = full & np.uint8(0xFC)
    for strict in (True, False):
        with LightCrafterEmulator(strict_levels=strict) as emu:
            client = LightCrafterClient(emu.host, emu.port)
            client.connect()
            client.set_sequence(bit_depth=6, count=16, trigger=1, exposure_us=25000,
                                period_us=27000, led=1)
            if strict:
                with pytest.raises(LightCrafterError, match="invalid parameter") as info:
                    client.define_pattern(0, encode_bmp(old[0]))
                assert info.value.code == 0x03 and 0 not in emu.state.patterns
            else:
                for i in range(16):
                    client.define_pattern(i, encode_bmp(old[i]))
                shown = np.stack([emu.state.patterns[i] for i in range(16)])
                intended = np.round(full.astype(np.float64) * 63 / 255)
                wrong = float(np.mean(shown != intended))
                print(f"old top-bits upload: {wrong:.1%} of pixels shown at a wrong level")
                assert wrong > 0.9
            client.close()
