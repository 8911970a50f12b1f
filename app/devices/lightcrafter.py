"""DLP LightCrafter (DLP3000 / DLPC300, DM365 host) over its TCP command interface.

Packet (TI DLPU007 "DLP LightCrafter DM365 Command Interface Guide", as we read it)::

    byte 0     packet type   0x00 busy · 0x01 error · 0x02 write · 0x03 write response
                             · 0x04 read · 0x05 read response
    byte 1, 2  CMD1, CMD2    command code, high byte first (0x0400 → 0x04, 0x00)
    byte 3     flags         0x00 complete · 0x01 first · 0x02 middle · 0x03 last of a multi-packet payload
    byte 4, 5  payload length, LSB then MSB (≤ 65535 per packet)
    payload
    checksum   sum of every preceding byte of the packet, mod 256

The device answers every packet (also each part of a multi-packet upload).
Commands used (payload layouts little-endian):

    0x0100 version (read)          1 byte: 0x00 DM365 sw · 0x10 FPGA · 0x20 MSP430 → ASCII string
    0x0101 display mode            1 byte: 0x00 static image · 0x01 test pattern · 0x02 HDMI · 0x04 pattern sequence
    0x0103 LED current             3 × uint16 R, G, B (0–1024)
    0x0400 pattern sequence setting  <BBBBIIIB: bit depth 1–8, pattern count, include inverted (0/1),
                                   input trigger (0x00 command · 0x01 auto/internal period · 0x02 external
                                   positive · 0x03 external negative), trigger delay µs, trigger period µs,
                                   exposure µs, LED select (0 red · 1 green · 2 blue)
    0x0401 pattern definition      1 byte pattern number + BMP file (608 × 684, 1- or 8-bit); multi-packet
    0x0402 start/stop sequence     1 byte: 1 start · 0 stop
    0x0403 advance sequence        no payload (command-trigger mode)
    0x0404 trigger output setting  <BBII: enable, polarity (0 rising · 1 falling), delay µs, pulse width µs
    0x0405 display pattern         uint16 pattern number

The DLPC300 frame memory holds 96 bit-planes: a sequence of n patterns gets bit depth
b = min(8, 96 // n) (16 fringe patterns → 6-bit). Patterns go up as 8-bit grayscale BMPs
quantised to b bits, most significant bits used (verify against the real firmware; the
fake server in lightcrafter_emulator.py accepts this layout).
"""

from __future__ import annotations

import contextlib
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

DEFAULT_PORT = 21845
DMD_WIDTH, DMD_HEIGHT = 608, 684
BIT_PLANES = 96
MAX_PAYLOAD = 65535
BUSY, ERROR, WRITE, WRITE_RESPONSE, READ, READ_RESPONSE = range(6)
COMPLETE, FIRST, MIDDLE, LAST = range(4)
CMD_VERSION, CMD_DISPLAY_MODE, CMD_LED_CURRENT = 0x0100, 0x0101, 0x0103
CMD_SEQ_SETTING, CMD_PATTERN_DEF, CMD_SEQ_START = 0x0400, 0x0401, 0x0402
CMD_SEQ_ADVANCE, CMD_TRIGGER_OUT, CMD_DISPLAY_PATTERN = 0x0403, 0x0404, 0x0405
MODE_STATIC, MODE_TEST_PATTERN, MODE_HDMI, MODE_PATTERN_SEQUENCE = 0x00, 0x01, 0x02, 0x04
TRIG_COMMAND, TRIG_AUTO, TRIG_EXT_POS, TRIG_EXT_NEG = 0x00, 0x01, 0x02, 0x03
LED_SELECT = {"red": 0, "green": 1, "blue": 2}
LED_CURRENT_MAX = 1024
SEQ_FORMAT = "<BBBBIIIB"
TRIGGER_OUT_FORMAT = "<BBII"
ERRORS = {
    0x01: "unknown error", 0x02: "invalid command", 0x03: "invalid parameter", 0x04: "out of memory",
    0x05: "hardware device failure", 0x06: "hardware busy", 0x07: "not initialised",
    0x08: "object not found", 0x09: "checksum error", 0x0A: "packet format error (payload size)",
    0x0B: "command continuation error (flags)",
}


class LightCrafterError(ProtocolError):
    """An error packet from the LightCrafter; ``code`` is its error byte."""

    def __init__(self, command: int, code: int) -> None:
        super().__init__(f"LightCrafter refused command 0x{command:04X}: {ERRORS.get(code, 'code')} (0x{code:02X})")
        self.command, self.code = command, code


def checksum(data: bytes) -> int:
    """Sum of the bytes mod 256."""
    return sum(data) & 0xFF


def encode_packet(ptype: int, command: int, payload: bytes = b"", flags: int = COMPLETE) -> bytes:
    """One framed packet (header, payload, checksum)."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload: at most {MAX_PAYLOAD} bytes per packet, got {len(payload)}")
    head = struct.pack("<BBBBH", ptype, command >> 8, command & 0xFF, flags, len(payload))
    body = head + payload
    return body + bytes([checksum(body)])


def split_packets(ptype: int, command: int, payload: bytes, max_payload: int = MAX_PAYLOAD) -> list[bytes]:
    """Frame ``payload`` as one packet, or as first/middle/last packets when it is too large."""
    if len(payload) <= max_payload:
        return [encode_packet(ptype, command, payload)]
    chunks = [payload[i:i + max_payload] for i in range(0, len(payload), max_payload)]
    flags = [FIRST] + [MIDDLE] * (len(chunks) - 2) + [LAST]
    return [encode_packet(ptype, command, c, f) for c, f in zip(chunks, flags, strict=True)]


def encode_bmp(image: npt.NDArray[np.uint8], bits: int = 8) -> bytes:
    """A Windows BMP (bottom-up, rows padded to 4 bytes) of a (H, W) uint8 image.

    ``bits=8``: 256-grey palette, one byte a pixel. ``bits=1``: 2-colour palette,
    a pixel is set where ``image >= 128``.
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
    info = struct.pack("<IiiHHIIiiII", 40, w, h, 1, bits, 0, pixels.size, 2835, 2835, len(palette), 0)
    return header + info + palette.tobytes() + pixels.tobytes()


def sequence_bit_depth(n_patterns: int) -> int:
    """Deepest bit depth at which ``n_patterns`` fit the 96 bit-planes (ValueError if none)."""
    if not 1 <= n_patterns <= BIT_PLANES:
        raise ValueError(f"n_patterns: the LightCrafter holds 1–{BIT_PLANES} patterns, got {n_patterns}")
    return min(8, BIT_PLANES // n_patterns)


class LightCrafterClient:
    """The packet protocol on one TCP connection; thread-safe, errors mapped to the device family."""

    def __init__(self, host: str, port: int = DEFAULT_PORT, *, timeout_s: float = 2.0,
                 busy_retries: int = 20, busy_wait_s: float = 0.05) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.busy_retries, self.busy_wait_s = busy_retries, busy_wait_s
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    def connect(self) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except TimeoutError:
            raise DeviceTimeout(f"{self.host}:{self.port}: connection timed out") from None
        except OSError as exc:
            raise DeviceNotFound(f"{self.host}:{self.port}: cannot connect ({exc.strerror or exc})") from None
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
        for _ in range(self.busy_retries + 1):
            try:
                self._sock_or_raise().sendall(packet)
                rtype, rcmd, payload = self._receive()
            except TimeoutError:
                raise DeviceTimeout(f"{self.host}:{self.port}: no reply to 0x{command:04X}") from None
            except OSError as exc:
                raise DeviceDisconnected(f"{self.host}:{self.port}: link lost ({exc})") from None
            if rtype == BUSY:
                time.sleep(self.busy_wait_s)
                continue
            if rtype == ERROR:
                raise LightCrafterError(command, payload[0] if payload else 0x01)
            expected = WRITE_RESPONSE if packet[0] == WRITE else READ_RESPONSE
            if rtype != expected or rcmd != command:
                raise ProtocolError(f"LightCrafter answered type {rtype} cmd 0x{rcmd:04X} to 0x{command:04X}")
            return payload
        raise DeviceTimeout(f"{self.host}:{self.port}: still busy after {self.busy_retries} retries")

    def _receive(self) -> tuple[int, int, bytes]:
        head = self._recv_exact(6)
        rtype, c1, c2, flags, length = struct.unpack("<BBBBH", head)
        rest = self._recv_exact(length + 1)
        payload, check = rest[:-1], rest[-1]
        if checksum(head + payload) != check:
            raise ProtocolError("LightCrafter reply has a bad checksum")
        if flags != COMPLETE:
            raise ProtocolError(f"LightCrafter reply with multi-packet flag {flags} is not supported")
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

    # --- commands ---------------------------------------------------------------------
    def version(self, which: int = 0x00) -> str:
        return self.request(READ, CMD_VERSION, bytes([which])).split(b"\0")[0].decode("ascii", "replace")

    def set_display_mode(self, mode: int) -> None:
        self.request(WRITE, CMD_DISPLAY_MODE, bytes([mode]))

    def set_led_current(self, red: int, green: int, blue: int) -> None:
        self.request(WRITE, CMD_LED_CURRENT, struct.pack("<HHH", red, green, blue))

    def set_sequence(self, *, bit_depth: int, count: int, trigger: int, exposure_us: int, period_us: int,
                     led: int, delay_us: int = 0, inverted: bool = False) -> None:
        payload = struct.pack(SEQ_FORMAT, bit_depth, count, int(inverted), trigger, delay_us, period_us,
                              exposure_us, led)
        self.request(WRITE, CMD_SEQ_SETTING, payload)

    def define_pattern(self, index: int, bmp: bytes) -> None:
        self.request(WRITE, CMD_PATTERN_DEF, bytes([index]) + bmp)

    def start_sequence(self, run: bool) -> None:
        self.request(WRITE, CMD_SEQ_START, bytes([int(run)]))

    def advance(self) -> None:
        self.request(WRITE, CMD_SEQ_ADVANCE)

    def set_trigger_out(self, *, enable: bool, falling: bool = False, delay_us: int = 0, width_us: int = 100) -> None:
        self.request(WRITE, CMD_TRIGGER_OUT, struct.pack(TRIGGER_OUT_FORMAT, int(enable), int(falling),
                                                         delay_us, width_us))

    def display_pattern(self, index: int) -> None:
        self.request(WRITE, CMD_DISPLAY_PATTERN, struct.pack("<H", index))


class LightCrafterProjector(Projector):
    """The fringe schedule on a LightCrafter 3000 (pattern-sequence mode, one LED, trigger out on).

    Args:
        dark_us: gap between one pattern's exposure and the next (pattern period = exposure + gap).
        trigger_delay_us, trigger_width_us: the trigger-output pulse to the camera (or controller).
    """

    def __init__(self, host: str, port: int = DEFAULT_PORT, *, timeout_s: float = 2.0, dark_us: int = 2000,
                 trigger_delay_us: int = 0, trigger_width_us: int = 100, name: str | None = None) -> None:
        super().__init__(name=name or f"LightCrafter({host}:{port})")
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.dark_us, self.trigger_delay_us, self.trigger_width_us = dark_us, trigger_delay_us, trigger_width_us
        self.firmware = ""
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
            self.firmware = client.version(0x00)
            with contextlib.suppress(LightCrafterError):  # some modes refuse "stop" when nothing runs
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
            client.start_sequence(False)
            client.set_led_current(0, 0, 0)
        except (DeviceDisconnected, DeviceTimeout, ProtocolError) as exc:
            self.log.debug("lights-off on close failed: %s", exc)
        finally:
            client.close()

    def _do_load(self, schedule: PatternSchedule, exposure_ms: float) -> None:
        bits = sequence_bit_depth(schedule.n_frames)
        if (schedule.width, schedule.height) != (DMD_WIDTH, DMD_HEIGHT):
            raise ValueError(f"schedule: the DLP3000 is {DMD_WIDTH}x{DMD_HEIGHT}, got {schedule.width}x{schedule.height}")
        client = self._c()
        client.start_sequence(False)
        self._send_sequence(schedule.n_frames, bits, self.led, self.trigger_mode, exposure_ms)
        keep = np.uint8((0xFF << (8 - bits)) & 0xFF)  # the b most significant bits
        for i, image in enumerate(generate_patterns(schedule)):
            client.define_pattern(i, encode_bmp(image & keep if bits < 8 else image, 8))
        client.set_trigger_out(enable=True, delay_us=self.trigger_delay_us, width_us=self.trigger_width_us)
        self.bit_depth = bits
        if self.state.value == "running":
            client.start_sequence(True)

    def _send_sequence(self, count: int, bits: int, led: str, mode: str, exposure_ms: float) -> None:
        exposure_us = round(exposure_ms * 1000)
        self._c().set_sequence(bit_depth=bits, count=count, trigger=TRIG_AUTO if mode == "internal" else TRIG_EXT_POS,
                               exposure_us=exposure_us, period_us=exposure_us + self.dark_us, led=LED_SELECT[led])

    def _resend_sequence(self, led: str, mode: str, exposure_ms: float | None = None) -> None:
        """The sequence setting alone (0x0400): same bit depth and count, so the patterns stay."""
        if self.schedule is None:
            return
        running = self.state.value == "running"
        if running:
            self._c().start_sequence(False)
        exp = self.exposure_ms if exposure_ms is None else exposure_ms
        self._send_sequence(self.schedule.n_frames, self.bit_depth, led, mode, exp)
        if running:
            self._c().start_sequence(True)

    def _do_set_exposure(self, exposure_ms: float) -> None:
        """The timing call: exposure and period in the sequence setting, no pattern upload."""
        if round(exposure_ms * 1000) != round(self.exposure_ms * 1000):
            self._resend_sequence(self.led, self.trigger_mode, exposure_ms)

    @staticmethod
    def _currents(led: str, current: float) -> tuple[int, int, int]:
        values = [0, 0, 0]
        values[LED_SELECT[led]] = round(current * LED_CURRENT_MAX)
        return values[0], values[1], values[2]

    def _do_set_led(self, led: str, current: float) -> None:
        self._c().set_led_current(*self._currents(led, current))
        if led != self.led:
            self._resend_sequence(led, self.trigger_mode)

    def _do_set_trigger_mode(self, mode: str) -> None:
        if mode != self.trigger_mode:
            self._resend_sequence(self.led, mode)

    def _do_start(self) -> None:
        self._c().start_sequence(True)

    def _do_stop(self) -> None:
        self._c().start_sequence(False)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "host": f"{self.host}:{self.port}", "firmware": self.firmware,
                "bit_depth": self.bit_depth}
