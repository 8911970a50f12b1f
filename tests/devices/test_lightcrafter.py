"""LightCrafter 3000 client against the emulator on 127.0.0.1: framing, uploads, faults.

The byte vectors from TI's guide are in test_lightcrafter_vectors.py.
"""

from __future__ import annotations

import io
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from app.devices import (
    DeviceDisconnected,
    DeviceNotFound,
    DeviceState,
    DeviceTimeout,
    ProtocolError,
)
from app.devices.lightcrafter import (
    CMD_PATTERN_DEF,
    CMD_SEQ_SETTING_EXT,
    CMD_SEQ_START,
    CMD_VERSION,
    FIRST,
    LAST,
    MIDDLE,
    READ,
    WRITE,
    LightCrafterClient,
    LightCrafterError,
    LightCrafterProjector,
    checksum,
    encode_bmp,
    encode_packet,
    quantise_levels,
    sequence_bit_depth,
    split_packets,
)
from app.devices.lightcrafter_emulator import LightCrafterEmulator, decode_bmp
from app.recon.patterns import PatternSchedule, generate_patterns
from tests.helpers.lightcrafter import raw_exchange

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def emu():
    e = LightCrafterEmulator().start()
    yield e
    e.stop()



def test_packet_bytes_match_known_lightcrafter_commands():
    # version read (DM365 software) and "display mode = static image", as sent to real units
    assert encode_packet(READ, CMD_VERSION, b"\x00") == bytes.fromhex("0401000001000006")
    assert encode_packet(WRITE, 0x0101, b"\x00") == bytes.fromhex("0201010001000005")
    assert checksum(bytes(range(256))) == (255 * 256 // 2) % 256


def test_large_payload_is_split_with_continuation_flags():
    payload = bytes(range(256)) * 700  # 179 200 bytes → 65535 + 65535 + 48130
    packets = split_packets(WRITE, CMD_PATTERN_DEF, payload)
    assert [p[3] for p in packets] == [FIRST, MIDDLE, LAST]
    assert [p[4] | p[5] << 8 for p in packets] == [65535, 65535, 48130]
    assert b"".join(p[6:-1] for p in packets) == payload
    assert all(p[-1] == sum(p[:-1]) % 256 for p in packets)


@pytest.mark.parametrize("bits", [1, 8])
def test_bmp_encoding_is_read_back_by_opencv_and_the_emulator(bits):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (684, 608), dtype=np.uint8)
    expected = img if bits == 8 else np.where(img >= 128, 255, 0).astype(np.uint8)
    bmp = encode_bmp(img, bits)
    decoded = cv2.imdecode(np.frombuffer(bmp, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(decoded, expected)
    # the emulator reads pixel values (what the DMD shows), not palette colours
    assert np.array_equal(decode_bmp(bmp), img if bits == 8 else (img >= 128).astype(np.uint8))


@pytest.mark.parametrize("bpp", [2, 4])
def test_bmp_of_2_and_4_bits_is_read_by_the_emulator_as_pillow_reads_it(bpp):
    """The guide allows 1-, 2-, 4- and 8-bit BMPs: one written here by hand (4-bit: as Pillow)."""
    rng = np.random.default_rng(bpp)
    h, w = 5, 13
    levels = rng.integers(0, 2**bpp, (h, w), dtype=np.uint8)
    per_byte = 8 // bpp
    stride = ((w * bpp + 7) // 8 + 3) // 4 * 4
    rows = bytearray()
    for row in levels[::-1]:  # bottom-up
        packed = bytearray(stride)
        for x, v in enumerate(row):
            packed[x // per_byte] |= int(v) << (8 - bpp * (x % per_byte + 1))
        rows += packed
    palette = b"".join(bytes([g, g, g, 0]) for g in range(0, 256, 256 // 2**bpp))
    offset = 14 + 40 + len(palette)
    bmp = (struct.pack("<2sIHHI", b"BM", offset + len(rows), 0, 0, offset)
           + struct.pack("<IiiHHIIiiII", 40, w, h, 1, bpp, 0, len(rows), 0, 0, 2**bpp, 0)
           + palette + bytes(rows))
    if bpp == 4:  # Pillow reads 1-, 4- and 8-bit palette BMPs, not 2-bit ones
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(bmp))), levels)
    assert np.array_equal(decode_bmp(bmp), levels)


def test_levels_are_quantised_into_the_least_significant_bits():
    img = np.array([[0, 1, 2, 127, 128, 252, 253, 255]], np.uint8)
    assert quantise_levels(img, 6).tolist() == [[0, 0, 0, 31, 32, 62, 63, 63]]
    assert quantise_levels(img, 8).tolist() == img.tolist()
    assert quantise_levels(img, 1).tolist() == [[0, 0, 0, 0, 1, 1, 1, 1]]
    with pytest.raises(ValueError, match="bits"):
        quantise_levels(img, 9)


def test_bit_depth_fits_the_96_bit_planes():
    assert [sequence_bit_depth(n) for n in (1, 12, 16, 24, 96)] == [8, 8, 6, 4, 1]
    with pytest.raises(ValueError, match="n_patterns"):
        sequence_bit_depth(97)


def test_server_answers_bad_checksum_and_continuation_errors_byte_exactly(emu):
    good = encode_packet(READ, CMD_VERSION, b"\x00")
    bad = good[:-1] + bytes([(good[-1] + 1) % 256])
    assert raw_exchange(emu, bad) == bytes([0x01, 0x01, 0x00, 0x00, 0x01, 0x00, 0x08, 0x0B])
    middle = encode_packet(WRITE, CMD_PATTERN_DEF, b"\x00" * 8, MIDDLE)
    assert raw_exchange(emu, middle)[6] == 0x0A
    reply = raw_exchange(emu, good)
    assert reply[0] == 0x05 and reply[-1] == sum(reply[:-1]) % 256
    assert reply[6:-1].startswith(b"5.0.0")


def test_projector_uploads_the_fringe_sequence(emu):
    schedule = PatternSchedule()
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    assert proj.firmware.startswith("5.0.0") and emu.state.display_mode == 0x04
    proj.load_schedule(schedule, exposure_ms=25.0)
    seq = emu.state.sequence
    assert seq == {"bit_depth": 6, "count": 16, "inverted": 0, "trigger": 0x01, "delay_us": 0,
                   "period_us": 27000, "exposure_us": 25000, "led": 1, "play_mode": 1}
    assert emu.state.sequence_command == 0x0480
    expected = np.round(generate_patterns(schedule) * (63 / 255))  # 6 LSBs, levels 0-63
    assert sorted(emu.state.patterns) == list(range(16))
    assert all(np.array_equal(emu.state.patterns[i], expected[i]) for i in range(16))
    assert emu.state.trigger_out == {"enable": 1, "source": 0, "polarity": 0, "delay_us": 0,
                                     "width_us": 100}
    proj.set_led("blue", current=0.5)
    assert emu.state.led_current == (0, 0, 137) and emu.state.sequence["led"] == 2
    proj.start()
    assert emu.state.running
    proj.stop()
    assert not emu.state.running
    proj.start()
    proj.close()
    assert not emu.state.running and emu.state.led_current == (0, 0, 0)  # lights off on close


def test_busy_replies_are_retried_then_time_out(emu):
    """Busy packets whose checksum is unset (the guide: bytes after the first are ignored)."""
    emu.busy_next = 1
    busy = raw_exchange(emu, encode_packet(READ, CMD_VERSION, b"\x00"))
    assert busy[0] == 0x00 and busy[-1] != sum(busy[:-1]) % 256
    client = LightCrafterClient(emu.host, emu.port, busy_retries=5, busy_wait_s=0.001)
    client.connect()
    emu.busy_next = 3
    assert client.version().startswith("5.0.0")
    emu.busy_next = 10
    with pytest.raises(DeviceTimeout, match="busy"):
        client.version()
    client.close()


def test_error_packets_become_protocol_errors(emu):
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    emu.fail_next = 0x04
    with pytest.raises(LightCrafterError, match="hardware failure") as info:
        proj.set_led("green", current=0.2)
    assert info.value.code == 0x04 and isinstance(info.value, ProtocolError)
    assert proj.state is DeviceState.OPEN
    proj.close()


def test_unplug_faults_and_replug_reuploads(emu):
    proj = LightCrafterProjector(emu.host, emu.port, timeout_s=1.0)
    proj.open()
    proj.load_schedule(PatternSchedule(), exposure_ms=20.0)
    proj.start()
    emu.stop()
    with pytest.raises(DeviceDisconnected):
        proj.set_led("red")
    assert proj.state is DeviceState.FAULT and "link lost" in proj.last_error
    with pytest.raises(DeviceNotFound):
        proj.open()
    emu.start()
    assert len(emu.state.patterns) == 0  # a power cycle forgot the patterns
    t0 = time.monotonic()
    proj.open()
    assert time.monotonic() - t0 < 2.0
    assert len(emu.state.patterns) == 16 and emu.state.sequence["count"] == 16
    proj.start()
    assert emu.state.running
    proj.close()


def test_cli_emulate_lightcrafter():
    proc = subprocess.Popen([sys.executable, "-m", "app", "emulate", "lightcrafter", "--port", "0"],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert proc.stdout is not None
        host, port = proc.stdout.readline().strip().rsplit(":", 1)
        client = LightCrafterClient(host, int(port))
        client.connect()
        assert client.version().startswith("5.0.0")
        client.close()
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0


def test_exposure_change_is_a_timing_call_without_pattern_upload(emu):
    """A new exposure sends only the sequence setting (stop, 0x0480, start): no re-upload."""
    schedule = PatternSchedule()
    proj = LightCrafterProjector(emu.host, emu.port)
    proj.open()
    before_load = emu.state.bytes_received
    proj.load_schedule(schedule, exposure_ms=25.0)
    upload_bytes = emu.state.bytes_received - before_load
    assert emu.state.commands.count(CMD_PATTERN_DEF) == 16 and upload_bytes > 16 * 608 * 684
    proj.start()
    patterns = {i: p.copy() for i, p in emu.state.patterns.items()}
    n_cmds, n_bytes = len(emu.state.commands), emu.state.bytes_received

    proj.set_exposure(40.0)

    sent = emu.state.commands[n_cmds:]
    assert sent == [CMD_SEQ_START, CMD_SEQ_SETTING_EXT, CMD_SEQ_START], [hex(c) for c in sent]
    assert emu.state.bytes_received - n_bytes < 64  # three small packets, not ~6.7 MB
    assert emu.state.sequence["exposure_us"] == 40000 and emu.state.sequence["period_us"] == 42000
    assert emu.state.running and proj.exposure_ms == 40.0
    assert sorted(emu.state.patterns) == list(range(16))
    assert all(np.array_equal(emu.state.patterns[i], patterns[i]) for i in range(16))

    n_cmds = len(emu.state.commands)
    proj.set_exposure(40.0)  # unchanged: nothing to send
    assert emu.state.commands[n_cmds:] == []
    with pytest.raises(ValueError, match="exposure_ms"):
        proj.set_exposure(0.1)
    assert emu.state.sequence["exposure_us"] == 40000
    proj.close()


def test_service_exposure_change_uses_the_timing_call(emu):
    """The acquisition's settings step (also auto-exposure's path) never re-uploads the patterns."""
    from app.config import Settings
    from app.service.devices import DeviceBundle, apply_settings, create_devices, start_devices

    sim = create_devices(Settings(viewer=False, sim_seed=0))
    proj = LightCrafterProjector(emu.host, emu.port)
    devs = DeviceBundle(sim.camera, proj, None, None)
    start_devices(devs, PatternSchedule(), exposure_ms=20.0, led="green", bit_depth=8)
    try:
        assert emu.state.commands.count(CMD_PATTERN_DEF) == 16 and emu.state.running
        n_cmds, n_bytes = len(emu.state.commands), emu.state.bytes_received
        for exposure_ms in (10.0, 15.0, 30.0, 12.5):  # an auto-exposure search's trials
            apply_settings(devs, exposure_ms=exposure_ms, led=None)
            assert sim.camera.settings.exposure_ms == exposure_ms
            assert emu.state.sequence["exposure_us"] == round(exposure_ms * 1000)
        assert CMD_PATTERN_DEF not in emu.state.commands[n_cmds:]
        assert emu.state.bytes_received - n_bytes < 4 * 64
    finally:
        proj.close()
        sim.camera.close()
