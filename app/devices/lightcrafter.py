"""DLP LightCrafter (DLP3000 / DLPC300, DM365 host) over its TCP command interface.

Follows TI's "DLP LightCrafter DM365 Command Interface Guide", DLPU007A (sections 2–3),
and TI's LightCrafter API sample code v2.0. Every packer below names the guide's table
it follows; the byte-exact vectors are in ``tests/devices/test_lightcrafter_vectors.py``.

Packet (guide §2)::

    byte 0     packet type   0x00 busy (only this byte counts) · 0x01 error · 0x02 write
                             · 0x03 write response · 0x04 read · 0x05 read response
    byte 1, 2  CMD1, CMD2    command code, high byte first (0x0480 → 0x04, 0x80)
    byte 3     flags         0x00 complete · 0x01 first · 0x02 middle · 0x03 last part
    byte 4, 5  payload length, little-endian (≤ 65535 per packet)
    payload    multi-byte numbers little-endian
    checksum   sum of every preceding byte of the packet, mod 256

The device answers every packet (also each part of a multi-packet upload); the host
waits for that answer before the next packet and re-sends a packet answered "busy".

The DLPC300 frame memory holds 96 bit-planes: a sequence of n patterns gets bit depth
b = min(8, 96 // n) (16 fringe patterns → 6-bit). A pattern goes up as an 8-bit BMP
whose levels are 0 … 2**b − 1: the device shows the b LEAST significant bits (§3.11).
"""

from __future__ import annotations

import contextlib
import re
import socket
import struct
import threading
import time
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.schedule import PatternSchedule
from app.devices.base import Projector
from app.devices.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout, ProtocolError
from app.recon.patterns import generate_patterns

DEFAULT_PORT = 0x5555  # 21845
DMD_WIDTH, DMD_HEIGHT = 608, 684
BIT_PLANES = 96
MAX_PAYLOAD = 65535
BUSY, ERROR, WRITE, WRITE_RESPONSE, READ, READ_RESPONSE = range(6)
COMPLETE, FIRST, MIDDLE, LAST = range(4)
CMD_VERSION, CMD_DISPLAY_MODE, CMD_TEST_PATTERN, CMD_LED_CURRENT = 0x0100, 0x0101, 0x0103, 0x0104
CMD_SEQ_SETTING, CMD_PATTERN_DEF, CMD_SEQ_START = 0x0400, 0x0401, 0x0402
CMD_SEQ_ADVANCE, CMD_TRIGGER_OUT, CMD_DISPLAY_PATTERN = 0x0403, 0x0404, 0x0405
CMD_SEQ_SETTING_EXT = 0x0480
VERSION_DM365, VERSION_FPGA, VERSION_MSP430 = 0x00, 0x10, 0x20
MODE_STATIC, MODE_TEST_PATTERN, MODE_HDMI, MODE_PATTERN_SEQUENCE = 0x00, 0x01, 0x02, 0x04
TRIG_COMMAND, TRIG_AUTO, TRIG_EXT_POS, TRIG_EXT_NEG = 0x00, 0x01, 0x02, 0x03
TRIG_CAMERA_POS, TRIG_CAMERA_NEG, TRIG_EXT_EXPOSURE = 0x04, 0x05, 0x06
PLAY_ONCE, PLAY_CONTINUOUS = 0, 1
LED_SELECT = {"red": 0, "green": 1, "blue": 2}
LED_CURRENT_MAX = 1024  # 2 A, short bursts only
LED_CURRENT_CONTINUOUS_MAX = 274  # 0x112 ≈ 633 mA: the continuous limit without active cooling
EXTENDED_SEQUENCE_FIRMWARE = 3  # DM365 firmware major version from which 0x0480 exists
SEQ_FORMAT = "<BBBBIIIB"  # 0x0400, 17 bytes
SEQ_EXT_FORMAT = "<BHBBIIIBB"  # 0x0480, 19 bytes
TRIGGER_OUT_FORMAT = "<BBBII"  # 0x0404, 11 bytes
LED_CURRENT_FORMAT = "<HHH"  # 0x0104, 6 bytes
E_UNKNOWN, E_INVALID_COMMAND, E_INVALID_PARAMETER, E_OUT_OF_MEMORY = 0x01, 0x02, 0x03, 0x04
E_BUSY, E_NOT_INITIALISED, E_NOT_FOUND, E_CHECKSUM = 0x05, 0x06, 0x07, 0x08
E_PAYLOAD_SIZE, E_CONTINUATION = 0x09, 0x0A
ERRORS = {  # the guide's error-code table (it lists 0x04 twice: memory and hardware failure)
    E_UNKNOWN: "unknown failure", E_INVALID_COMMAND: "invalid command",
    E_INVALID_PARAMETER: "invalid parameter",
    E_OUT_OF_MEMORY: "out of memory or hardware failure", E_BUSY: "hardware busy",
    E_NOT_INITIALISED: "not initialised", E_NOT_FOUND: "object not found",
    E_CHECKSUM: "checksum error", E_PAYLOAD_SIZE: "payload size wrong for the command",
    E_CONTINUATION: "wrong continuation flag",
}


class LightCrafterError(ProtocolError):
    """An error packet from the LightCrafter; ``code`` is its error byte."""

    def __init__(self, command: int, code: int) -> None:
        reason = ERRORS.get(code, "undocumented error")
        super().__init__(f"LightCrafter refused command 0x{command:04X}: {reason} (0x{code:02X})")
        self.command, self.code = command, code


def checksum(data: bytes) -> int:
    """Sum of the bytes mod 256."""
    return sum(data) & 0xFF


def encode_packet(ptype: int, command: int, payload: bytes = b"", flags: int = COMPLETE) -> bytes:
    """One framed packet (header, payload, checksum), guide §2."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload: at most {MAX_PAYLOAD} bytes per packet, got {len(payload)}")
    head = struct.pack("<BBBBH", ptype, command >> 8, command & 0xFF, flags, len(payload))
    body = head + payload
    return body + bytes([checksum(body)])


def split_packets(ptype: int, command: int, payload: bytes,
                  max_payload: int = MAX_PAYLOAD) -> list[bytes]:
    """Frame ``payload`` as one packet, or as first/middle/last packets when it is too large."""
    if len(payload) <= max_payload:
        return [encode_packet(ptype, command, payload)]
    chunks = [payload[i:i + max_payload] for i in range(0, len(payload), max_payload)]
    flags = [FIRST] + [MIDDLE] * (len(chunks) - 2) + [LAST]
    return [encode_packet(ptype, command, c, f) for c, f in zip(chunks, flags, strict=True)]


def _uint(name: str, value: int, low: int, high: int) -> int:
    if isinstance(value, bool) or int(value) != value or not low <= int(value) <= high:
        raise ValueError(f"{name}: need an integer within {low}–{high}, got {value!r}")
    return int(value)


def pack_led_current(red: int, green: int, blue: int) -> bytes:
    """Payload of 0x0104 "LED Current" (DLPU007A, LED current table): 3 × uint16, 0–1024.

    Not 0x0103, which is "Current Test Pattern" (one byte).
    """
    return struct.pack(LED_CURRENT_FORMAT, _uint("red", red, 0, LED_CURRENT_MAX),
                       _uint("green", green, 0, LED_CURRENT_MAX),
                       _uint("blue", blue, 0, LED_CURRENT_MAX))


def pack_sequence(*, bit_depth: int, count: int, trigger: int, delay_us: int, period_us: int,
                  exposure_us: int, led: int, inverted: bool = False, extended: bool = True,
                  play_mode: int = PLAY_CONTINUOUS) -> bytes:
    """Payload of the pattern sequence setting (DLPU007A, 0x0400 / 0x0480 tables).

    ``extended``: 0x0480 (19 bytes, firmware ≥ 3.0, TI's v2.0 code): count as uint16 and a
    trailing play-mode byte. Otherwise the legacy 0x0400 (17 bytes, count one byte, no play
    mode). Times in µs (uint32); ``led`` 0 red · 1 green · 2 blue; ``trigger`` 0–6.
    """
    _uint("bit_depth", bit_depth, 1, 8)
    _uint("count", count, 1, 1000 if extended else 96)
    _uint("trigger", trigger, 0, 6)
    _uint("led", led, 0, 2)
    for name, v in (("delay_us", delay_us), ("period_us", period_us),
                    ("exposure_us", exposure_us)):
        _uint(name, v, 0, 0xFFFFFFFF)
    if not extended:
        return struct.pack(SEQ_FORMAT, bit_depth, count, int(inverted), trigger, delay_us,
                           period_us, exposure_us, led)
    return struct.pack(SEQ_EXT_FORMAT, bit_depth, count, int(inverted), trigger, delay_us,
                       period_us, exposure_us, led, _uint("play_mode", play_mode, 0, 1))


def pack_trigger_out(*, enable: bool, source: int = 0, falling: bool = False, delay_us: int = 0,
                     width_us: int = 100) -> bytes:
    """Payload of 0x0404 "Trigger Output Setting" (DLPU007A table; TI's code): 11 bytes.

    enable, trigger source, polarity (0 positive · 1 negative), delay µs (uint32), pulse
    width µs (uint32). The guide does not enumerate the source values; 0 is sent.
    """
    return struct.pack(TRIGGER_OUT_FORMAT, int(enable), _uint("source", source, 0, 255),
                       int(falling), _uint("delay_us", delay_us, 0, 0xFFFFFFFF),
                       _uint("width_us", width_us, 1, 0xFFFFFFFF))


def encode_bmp(image: npt.NDArray[np.uint8], bits: int = 8) -> bytes:
    """A Windows BMP (bottom-up, rows padded to 4 bytes) of a (H, W) uint8 image.

    ``bits=8``: 256-grey palette, one byte a pixel, the values as given. ``bits=1``:
    2-colour palette, a pixel is set where ``image >= 128``.
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"image: expected (H, W) uint8, got {img.shape} {img.dtype}")
    if bits not in (1, 8):
        raise ValueError(f"bits: must be 1 or 8, got {bits}")
    h, w = img.shape
    if bits == 8:
        rows = img
        palette = np.repeat(np.arange(256, dtype=np.uint8), 4).reshape(256, 4)
    else:
        rows = np.packbits(img >= 128, axis=1)
        palette = np.array([[0, 0, 0, 0], [255, 255, 255, 0]], np.uint8)
    stride = (rows.shape[1] + 3) // 4 * 4
    pixels = np.zeros((h, stride), np.uint8)
    pixels[:, : rows.shape[1]] = rows[::-1]
    offset = 14 + 40 + palette.size
    size = offset + pixels.size
    header = struct.pack("<2sIHHI", b"BM", size, 0, 0, offset)
    info = struct.pack("<IiiHHIIiiII", 40, w, h, 1, bits, 0, pixels.size, 2835, 2835,
                       len(palette), 0)
    return header + info + palette.tobytes() + pixels.tobytes()


def quantise_levels(image: npt.NDArray[np.uint8], bits: int) -> npt.NDArray[np.uint8]:
    """A full-range (H, W) uint8 pattern as the ``bits`` least significant bits (§3.11).

    Levels 0–255 map to 0 … 2**bits − 1 by rounding (255 → 2**bits − 1): the device shows
    only the low ``bits`` bits of each uploaded byte, so a top-bits image would wrap.
    """
    _uint("bits", bits, 1, 8)
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"image: expected (H, W) uint8, got {img.shape} {img.dtype}")
    top = (1 << bits) - 1
    return ((img.astype(np.uint32) * top + 127) // 255).astype(np.uint8)


def sequence_bit_depth(n_patterns: int) -> int:
    """Deepest bit depth at which ``n_patterns`` fit the 96 bit-planes (ValueError if none)."""
    if not 1 <= n_patterns <= BIT_PLANES:
        raise ValueError(
            f"n_patterns: the LightCrafter holds 1–{BIT_PLANES} patterns, got {n_patterns}")
    return min(8, BIT_PLANES // n_patterns)


def firmware_major(version: str) -> int | None:
    """Major number of a version string such as ``"5.0.0"`` (None if none is found)."""
    match = re.search(r"(\d+)\.\d+", version)
    return int(match.group(1)) if match else None


class LightCrafterClient:
    """The packet protocol on one TCP connection; thread-safe, errors in the device family."""

    def __init__(self, host: str, port: int = DEFAULT_PORT, *, timeout_s: float = 2.0,
                 busy_retries: int = 20, busy_wait_s: float = 0.05) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.busy_retries, self.busy_wait_s = busy_retries, busy_wait_s
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    def connect(self) -> None:
        where = f"{self.host}:{self.port}"
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except TimeoutError:
            raise DeviceTimeout(f"{where}: connection timed out") from None
        except OSError as exc:
            raise DeviceNotFound(f"{where}: cannot connect ({exc.strerror or exc})") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def request(self, ptype: int, command: int, payload: bytes = b"") -> bytes:
        """Send a write/read command (split if large); return the last response's payload."""
        with self._lock:
            reply = b""
            for packet in split_packets(ptype, command, payload):
                reply = self._exchange(packet, command)
            return reply

    def _exchange(self, packet: bytes, command: int) -> bytes:
        where = f"{self.host}:{self.port}"
        for _ in range(self.busy_retries + 1):
            try:
                self._sock_or_raise().sendall(packet)
                rtype, rcmd, payload = self._receive()
            except TimeoutError:
                raise DeviceTimeout(f"{where}: no reply to 0x{command:04X}") from None
            except OSError as exc:
                raise DeviceDisconnected(f"{where}: link lost ({exc})") from None
            if rtype == BUSY:
                time.sleep(self.busy_wait_s)
                continue
            if rtype == ERROR:
                raise LightCrafterError(command, payload[0] if payload else E_UNKNOWN)
            expected = WRITE_RESPONSE if packet[0] == WRITE else READ_RESPONSE
            if rtype != expected or rcmd != command:
                raise ProtocolError(
                    f"LightCrafter answered type {rtype} cmd 0x{rcmd:04X} to 0x{command:04X}")
            return payload
        raise DeviceTimeout(f"{where}: still busy after {self.busy_retries} retries")

    def _receive(self) -> tuple[int, int, bytes]:
        head = self._recv_exact(6)
        rtype, c1, c2, flags, length = struct.unpack("<BBBBH", head)
        rest = self._recv_exact(length + 1)
        if rtype == BUSY:  # guide §2: only the first byte of a busy packet is meaningful
            return BUSY, 0, b""
        payload, check = rest[:-1], rest[-1]
        if checksum(head + payload) != check:
            raise ProtocolError("LightCrafter reply has a bad checksum")
        if flags != COMPLETE:
            raise ProtocolError(
                f"LightCrafter reply with multi-packet flag {flags} is not supported")
        return rtype, (c1 << 8) | c2, payload

    def _recv_exact(self, n: int) -> bytes:
        sock, buf = self._sock_or_raise(), bytearray()
        while len(buf) < n:
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError("connection closed by the projector")
            buf += chunk
        return bytes(buf)

    def _sock_or_raise(self) -> socket.socket:
        if self._sock is None:
            raise ConnectionResetError("not connected")
        return self._sock

    # --- commands (payloads from the packers above) -----------------------------------
    def version(self, which: int = VERSION_DM365) -> str:
        """0x0100 read: 0x00 DM365 software, 0x10 FPGA, 0x20 MSP430 → ASCII string."""
        reply = self.request(READ, CMD_VERSION, bytes([which]))
        return reply.split(b"\0")[0].decode("ascii", "replace")

    def display_mode(self) -> int:
        """0x0101 read: the display mode byte."""
        reply = self.request(READ, CMD_DISPLAY_MODE)
        if len(reply) != 1:
            raise ProtocolError(f"LightCrafter display mode reply of {len(reply)} bytes, not 1")
        return reply[0]

    def set_display_mode(self, mode: int) -> None:
        """0x0101 write: 0 static image, 1 test pattern, 2 HDMI, 4 pattern sequence."""
        self.request(WRITE, CMD_DISPLAY_MODE, bytes([mode]))

    def led_current(self) -> tuple[int, int, int]:
        """0x0104 read: red, green, blue current codes."""
        reply = self.request(READ, CMD_LED_CURRENT)
        if len(reply) != 6:
            raise ProtocolError(f"LightCrafter LED current reply of {len(reply)} bytes, not 6")
        red, green, blue = struct.unpack(LED_CURRENT_FORMAT, reply)
        return red, green, blue

    def set_led_current(self, red: int, green: int, blue: int) -> None:
        self.request(WRITE, CMD_LED_CURRENT, pack_led_current(red, green, blue))

    def set_sequence(self, *, bit_depth: int, count: int, trigger: int, exposure_us: int,
                     period_us: int, led: int, delay_us: int = 0, inverted: bool = False,
                     extended: bool = True, play_mode: int = PLAY_CONTINUOUS) -> None:
        """0x0480 (``extended``) or the legacy 0x0400 pattern sequence setting."""
        payload = pack_sequence(bit_depth=bit_depth, count=count, trigger=trigger,
                                delay_us=delay_us, period_us=period_us,
                                exposure_us=exposure_us, led=led, inverted=inverted,
                                extended=extended, play_mode=play_mode)
        self.request(WRITE, CMD_SEQ_SETTING_EXT if extended else CMD_SEQ_SETTING, payload)

    def define_pattern(self, index: int, bmp: bytes) -> None:
        """0x0401: pattern number byte + BMP, split over packets by the flags (§3.11)."""
        self.request(WRITE, CMD_PATTERN_DEF, bytes([_uint("index", index, 0, 255)]) + bmp)

    def start_sequence(self, run: bool) -> None:
        """0x0402: 1 start, 0 stop."""
        self.request(WRITE, CMD_SEQ_START, bytes([int(run)]))

    def advance(self) -> None:
        """0x0403: next pattern (command-trigger mode), no payload."""
        self.request(WRITE, CMD_SEQ_ADVANCE)

    def set_trigger_out(self, *, enable: bool, source: int = 0, falling: bool = False,
                        delay_us: int = 0, width_us: int = 100) -> None:
        self.request(WRITE, CMD_TRIGGER_OUT,
                     pack_trigger_out(enable=enable, source=source, falling=falling,
                                      delay_us=delay_us, width_us=width_us))

    def trigger_out(self) -> dict[str, int]:
        """0x0404 read: the trigger-output setting (enable, source, polarity, delay, width)."""
        reply = self.request(READ, CMD_TRIGGER_OUT)
        if len(reply) != 11:
            raise ProtocolError(f"LightCrafter trigger output reply of {len(reply)} bytes, not 11")
        enable, source, polarity, delay_us, width_us = struct.unpack(TRIGGER_OUT_FORMAT, reply)
        return {"enable": enable, "source": source, "polarity": polarity, "delay_us": delay_us,
                "width_us": width_us}

    def display_pattern(self, index: int) -> None:
        """0x0405 (firmware ≥ 3.0): uint16 pattern number."""
        self.request(WRITE, CMD_DISPLAY_PATTERN, struct.pack("<H", index))


class LightCrafterProjector(Projector):
    """The fringe schedule on a LightCrafter 3000 (pattern-sequence mode, one LED, trigger out).

    Args:
        dark_us: gap between one pattern's exposure and the next (period = exposure + gap).
        trigger_delay_us, trigger_width_us: the trigger-output pulse to the camera.
        led_current_max: the LED current code a current fraction of 1.0 maps to; default
            the continuous limit without active cooling (274 ≈ 633 mA), at most 1024 (2 A).
    """

    def __init__(self, host: str, port: int = DEFAULT_PORT, *, timeout_s: float = 2.0,
                 dark_us: int = 2000, trigger_delay_us: int = 0, trigger_width_us: int = 100,
                 led_current_max: int = LED_CURRENT_CONTINUOUS_MAX,
                 name: str | None = None) -> None:
        super().__init__(name=name or f"LightCrafter({host}:{port})")
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.dark_us = dark_us
        self.trigger_delay_us, self.trigger_width_us = trigger_delay_us, trigger_width_us
        self.led_current_max = _uint("led_current_max", led_current_max, 1, LED_CURRENT_MAX)
        self.firmware = ""
        self.extended_sequence = True
        self.bit_depth = 0
        self._client: LightCrafterClient | None = None

    def _c(self) -> LightCrafterClient:
        if self._client is None:
            raise DeviceDisconnected("not connected")
        return self._client

    def _do_open(self) -> None:
        client = LightCrafterClient(self.host, self.port, timeout_s=self.timeout_s)
        client.connect()
        try:
            self.firmware = client.version(VERSION_DM365)
            major = firmware_major(self.firmware)
            # 0x0480 from firmware 3.0 on (later firmware may not answer 0x0400); TI's
            # v2.0 code sends it, so an unreadable version gets it too
            self.extended_sequence = major is None or major >= EXTENDED_SEQUENCE_FIRMWARE
            with contextlib.suppress(LightCrafterError):  # "stop" refused when nothing runs
                client.start_sequence(False)
            client.set_display_mode(MODE_PATTERN_SEQUENCE)
            client.set_led_current(*self._currents(self.led, self.led_current))
        except BaseException:
            client.close()
            raise
        self._client = client
        if self.schedule is not None:  # reconnect: the device lost its memory with its power
            self._do_load(self.schedule, self.exposure_ms)

    def _do_close(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        try:  # lights off where the link allows
            if self.state.value != "running":  # running: close() has just sent the stop
                client.start_sequence(False)
            client.set_led_current(0, 0, 0)
        except (DeviceDisconnected, DeviceTimeout, ProtocolError) as exc:
            self.log.debug("lights-off on close failed: %s", exc)
        finally:
            client.close()

    def _do_load(self, schedule: PatternSchedule, exposure_ms: float) -> None:
        bits = sequence_bit_depth(schedule.n_frames)
        if (schedule.width, schedule.height) != (DMD_WIDTH, DMD_HEIGHT):
            raise ValueError(f"schedule: the DLP3000 is {DMD_WIDTH}x{DMD_HEIGHT}, "
                             f"got {schedule.width}x{schedule.height}")
        client = self._c()
        client.start_sequence(False)
        self._send_sequence(schedule.n_frames, bits, self.led, exposure_ms)
        for i, image in enumerate(generate_patterns(schedule)):
            client.define_pattern(i, encode_bmp(quantise_levels(image, bits), 8))
        client.set_trigger_out(enable=True, delay_us=self.trigger_delay_us,
                               width_us=self.trigger_width_us)
        self.bit_depth = bits
        if self.state.value == "running":
            client.start_sequence(True)

    def _send_sequence(self, count: int, bits: int, led: str, exposure_ms: float) -> None:
        exposure_us = round(exposure_ms * 1000)
        # the projector's own clock paces the set; the camera follows its trigger out
        self._c().set_sequence(bit_depth=bits, count=count, trigger=TRIG_AUTO,
                               exposure_us=exposure_us, period_us=exposure_us + self.dark_us,
                               led=LED_SELECT[led], extended=self.extended_sequence)

    def _resend_sequence(self, led: str, exposure_ms: float | None = None) -> None:
        """The sequence setting alone: same bit depth and count, so the patterns stay."""
        if self.schedule is None:
            return
        running = self.state.value == "running"
        if running:
            self._c().start_sequence(False)
        exp = self.exposure_ms if exposure_ms is None else exposure_ms
        self._send_sequence(self.schedule.n_frames, self.bit_depth, led, exp)
        if running:
            self._c().start_sequence(True)

    def _do_set_exposure(self, exposure_ms: float) -> None:
        """The timing call: exposure and period in the sequence setting, no pattern upload."""
        if round(exposure_ms * 1000) != round(self.exposure_ms * 1000):
            self._resend_sequence(self.led, exposure_ms)

    def _currents(self, led: str, current: float) -> tuple[int, int, int]:
        values = [0, 0, 0]
        values[LED_SELECT[led]] = round(current * self.led_current_max)
        return values[0], values[1], values[2]

    def _do_set_led(self, led: str, current: float) -> None:
        self._c().set_led_current(*self._currents(led, current))
        if led != self.led:
            self._resend_sequence(led)

    def _do_start(self) -> None:
        self._c().start_sequence(True)

    def _do_stop(self) -> None:
        self._c().start_sequence(False)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "host": f"{self.host}:{self.port}",
                "firmware": self.firmware, "bit_depth": self.bit_depth,
                "sequence_command": f"0x{self._sequence_command():04X}"}

    def _sequence_command(self) -> int:
        return CMD_SEQ_SETTING_EXT if self.extended_sequence else CMD_SEQ_SETTING
