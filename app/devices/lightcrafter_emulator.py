"""A fake LightCrafter 3000: the DM365 TCP command interface, built from TI's guide.

The command table below is transcribed from DLPU007A's field tables (see
``/work/shared/lightcrafter-protocol.md`` in the project's notes), not from the client:
this module imports nothing from :mod:`app.devices.lightcrafter`, so a framing or
field bug on one side shows as a refusal on the other. Each packet is checked as the
device checks it — checksum, continuation flags, packet type, payload size per command,
the range of every field — and refused with the guide's error code:

    0x01 unknown · 0x02 invalid command · 0x03 invalid parameter · 0x04 out of memory
    · 0x05 hardware busy · 0x06 not initialised · 0x07 object not found · 0x08 checksum
    · 0x09 payload size wrong for the command · 0x0A wrong continuation flag

A pattern (0x0401) is kept as the device shows it: the least significant ``bit depth``
bits of each pixel (§3.11). With ``strict_levels`` (the default) a pattern holding a
level the bit depth cannot show is refused with 0x03; the device itself would show the
wrapped low bits, which is never what a host means, so the emulator makes it loud.

Faults: ``busy_next`` (that many packets answered "busy", checksum unset as the guide
allows), ``fail_next`` (an error code for the next command), ``refuse`` (an error code
for every (packet type, command), e.g. a read this firmware lacks), :meth:`stop` /
:meth:`start` (unplug / replug; a power cycle forgets everything).
"""

from __future__ import annotations

import contextlib
import logging
import re
import socket
import struct
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

log = logging.getLogger("fringescope.devices.lightcrafter_emulator")

WIDTH, HEIGHT = 608, 684
BIT_PLANES = 96
# packet types (guide §2)
T_BUSY, T_ERROR, T_WRITE, T_WRITE_RESP, T_READ, T_READ_RESP = 0x00, 0x01, 0x02, 0x03, 0x04, 0x05
# flags
F_COMPLETE, F_FIRST, F_MIDDLE, F_LAST = 0x00, 0x01, 0x02, 0x03
# error codes (guide's table)
E_UNKNOWN, E_INVALID_COMMAND, E_INVALID_PARAMETER, E_OUT_OF_MEMORY = 0x01, 0x02, 0x03, 0x04
E_BUSY, E_NOT_INITIALISED, E_NOT_FOUND, E_CHECKSUM = 0x05, 0x06, 0x07, 0x08
E_PAYLOAD_SIZE, E_CONTINUATION = 0x09, 0x0A
VERSION_SELECT = (0x00, 0x10, 0x20)  # DM365 software, FPGA, MSP430
DISPLAY_MODES = (0x00, 0x01, 0x02, 0x04)  # static, internal test pattern, HDMI, sequence
LAST_TEST_PATTERN = 0x0D
LED_CURRENT_MAX, LED_CURRENT_DEFAULT = 1024, 274
PACKET_LOG = 4096  # packets kept in ``state.packets`` (each cut to its first 64 bytes)


@dataclass(frozen=True)
class Command:
    """One row of the guide's command table.

    ``write_size``/``read_size``: the payload the host sends with a write / read (None: the
    direction does not exist; -1: variable). ``min_firmware``: the DM365 major version
    from which the command exists.
    """

    name: str
    write_size: int | None
    read_size: int | None
    min_firmware: int = 0


COMMANDS: dict[int, Command] = {
    0x0100: Command("version string", None, 1),
    0x0101: Command("display mode", 1, 0),
    0x0103: Command("internal test pattern", 1, 0),
    0x0104: Command("LED current", 6, 0),
    0x0400: Command("pattern sequence setting (legacy)", 17, 0),
    0x0401: Command("pattern definition", -1, None),
    0x0402: Command("start / stop sequence", 1, None),
    0x0403: Command("advance pattern", 0, None),
    0x0404: Command("trigger output setting", 11, 0),
    0x0405: Command("display pattern", 2, None, min_firmware=3),
    0x0480: Command("extended pattern sequence setting", 19, 0, min_firmware=3),
}


class Refused(Exception):
    """A command the device answers with an error packet; ``code`` is the error byte."""

    def __init__(self, code: int) -> None:
        super().__init__(f"error 0x{code:02X}")
        self.code = code


def _check(ok: bool, code: int = E_INVALID_PARAMETER) -> None:
    if not ok:
        raise Refused(code)


def decode_bmp(data: bytes) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 pixel values of an uncompressed 1-, 2-, 4- or 8-bit BMP.

    The values are the pixel data (palette indices), which is what the DMD shows; the
    palette is not applied. Refuses (``Refused``) what the device could not read.
    """
    _check(len(data) >= 54 and data[:2] == b"BM")
    offset = struct.unpack_from("<I", data, 10)[0]
    header_size, w, h, planes, bits, compression = struct.unpack_from("<IiiHHI", data, 14)
    _check(header_size >= 40 and planes == 1 and bits in (1, 2, 4, 8) and compression == 0)
    _check(w > 0 and h != 0)
    stride = ((w * bits + 7) // 8 + 3) // 4 * 4
    _check(offset >= 54 and len(data) >= offset + stride * abs(h), E_PAYLOAD_SIZE)
    rows = np.frombuffer(data, np.uint8, stride * abs(h), offset).reshape(abs(h), stride)
    if bits == 8:
        img = rows[:, :w].copy()
    else:
        per_byte = 8 // bits
        shifts = np.arange(8 - bits, -1, -bits, dtype=np.uint8)  # leftmost pixel in the MSBs
        vals = (rows[:, :, None] >> shifts) & np.uint8((1 << bits) - 1)
        img = vals.reshape(abs(h), stride * per_byte)[:, :w].astype(np.uint8)
    return img[::-1] if h > 0 else img


@dataclass
class LightCrafterState:
    """What the projector holds; ``patterns`` are the levels it shows (0 … 2**bits − 1)."""

    display_mode: int = 0x00
    test_pattern: int = 0x00
    led_current: tuple[int, int, int] = (LED_CURRENT_DEFAULT,) * 3
    sequence: dict[str, int] = field(default_factory=dict)
    sequence_command: int = 0
    trigger_out: dict[str, int] = field(default_factory=dict)
    patterns: dict[int, npt.NDArray[np.uint8]] = field(default_factory=dict)
    running: bool = False
    shown: int = 0
    advances: int = 0
    commands: list[int] = field(default_factory=list)  # every command that was carried out
    refusals: list[tuple[int, int]] = field(default_factory=list)  # (command, error code)
    packets: deque[bytes] = field(default_factory=lambda: deque(maxlen=PACKET_LOG))
    bytes_received: int = 0  # every packet byte read (uploads are ~420 kB a pattern)


class LightCrafterEmulator:
    """Serve the protocol on ``host:port`` (port 0: pick a free one; see ``.port``).

    Args:
        firmware: the DM365 software version string (0x0100, 0x00); its major number
            decides whether 0x0480 and 0x0405 exist (≥ 3).
        strict_levels: refuse (0x03) a pattern with levels above its bit depth.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, firmware: str = "5.0.0",
                 strict_levels: bool = True) -> None:
        self.host, self.port = host, port
        self.firmware, self.strict_levels = firmware, strict_levels
        match = re.search(r"(\d+)\.\d+", firmware)
        self.firmware_major = int(match.group(1)) if match else 0
        self.state = LightCrafterState()
        self.busy_next = 0
        self.fail_next: int | None = None
        self.refuse: dict[tuple[int, int], int] = {}
        self._server: socket.socket | None = None
        self._conns: set[socket.socket] = set()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._handlers: dict[int, Callable[[bytes], None]] = {
            0x0101: self._display_mode, 0x0103: self._test_pattern, 0x0104: self._led_current,
            0x0400: self._sequence_legacy, 0x0480: self._sequence_extended,
            0x0401: self._pattern, 0x0402: self._start_stop, 0x0403: self._advance,
            0x0404: self._trigger_out, 0x0405: self._display_pattern,
        }

    # --- lifecycle -------------------------------------------------------------------------
    def start(self) -> LightCrafterEmulator:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind((self.host, self.port))
        server.listen(4)
        self.port = server.getsockname()[1]
        self._server = server
        self.state = LightCrafterState()  # a power cycle forgets everything
        t = threading.Thread(target=self._accept, args=(server,), name="lightcrafter-emulator",
                             daemon=True)
        t.start()
        self._threads = [t]
        log.info("LightCrafter emulator on %s:%d", self.host, self.port)
        return self

    def stop(self) -> None:
        """Close the listener and every connection (clients see a reset / EOF)."""
        server, self._server = self._server, None
        if server is not None:
            with contextlib.suppress(OSError):
                server.shutdown(socket.SHUT_RDWR)
            server.close()
        with self._lock:
            conns, self._conns = list(self._conns), set()
        for conn in conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()
        for t in self._threads:
            t.join(timeout=2.0)

    def __enter__(self) -> LightCrafterEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _accept(self, server: socket.socket) -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            with self._lock:
                self._conns.add(conn)
            t = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            t.start()
            self._threads.append(t)

    # --- one connection --------------------------------------------------------------------
    def _serve(self, conn: socket.socket) -> None:
        pending: tuple[int, int, bytearray] | None = None  # (type, command, payload so far)
        try:
            while True:
                head = self._read(conn, 6)
                if head is None:
                    return
                ptype, cmd, flags = head[0], (head[1] << 8) | head[2], head[3]
                rest = self._read(conn, (head[4] | head[5] << 8) + 1)
                if rest is None:
                    return
                payload, check = rest[:-1], rest[-1]
                self.state.bytes_received += len(head) + len(rest)
                self.state.packets.append((head + rest)[:64])
                if sum(head + payload) % 256 != check:
                    self._refuse(conn, cmd, E_CHECKSUM)
                    continue
                if self.busy_next > 0:
                    self.busy_next -= 1
                    conn.sendall(bytes([T_BUSY, head[1], head[2], 0, 0, 0, 0]))  # checksum unset
                    continue
                try:
                    pending, reply = self._packet(ptype, cmd, flags, payload, pending)
                except Refused as exc:
                    pending = None
                    self._refuse(conn, cmd, exc.code)
                    continue
                self._send(conn, T_READ_RESP if ptype == T_READ else T_WRITE_RESP, cmd, reply)
        except OSError:
            return
        finally:
            with self._lock:
                self._conns.discard(conn)
            conn.close()

    @staticmethod
    def _read(conn: socket.socket, n: int) -> bytes | None:
        buf = bytearray()
        while len(buf) < n:
            chunk = conn.recv(n - len(buf))
            if not chunk:
                return None
            buf += chunk
        return bytes(buf)

    @staticmethod
    def _send(conn: socket.socket, ptype: int, cmd: int, payload: bytes) -> None:
        n = len(payload)
        packet = bytes([ptype, cmd >> 8, cmd & 0xFF, F_COMPLETE, n & 0xFF, n >> 8]) + payload
        conn.sendall(packet + bytes([sum(packet) % 256]))

    def _refuse(self, conn: socket.socket, cmd: int, code: int) -> None:
        self.state.refusals.append((cmd, code))
        self._send(conn, T_ERROR, cmd, bytes([code]))

    def _packet(
        self, ptype: int, cmd: int, flags: int, payload: bytes,
        pending: tuple[int, int, bytearray] | None,
    ) -> tuple[tuple[int, int, bytearray] | None, bytes]:
        """Reassemble multi-packet payloads (every part is answered); run the command."""
        _check(flags in (F_COMPLETE, F_FIRST, F_MIDDLE, F_LAST), E_CONTINUATION)
        if flags in (F_MIDDLE, F_LAST):
            _check(pending is not None and pending[:2] == (ptype, cmd), E_CONTINUATION)
        else:
            _check(pending is None, E_CONTINUATION)
        if flags == F_FIRST:
            return (ptype, cmd, bytearray(payload)), b""
        if flags == F_MIDDLE:
            assert pending is not None
            pending[2].extend(payload)
            return pending, b""
        if flags == F_LAST:
            assert pending is not None
            payload = bytes(pending[2] + payload)
        return None, self._execute(ptype, cmd, payload)

    def _execute(self, ptype: int, cmd: int, payload: bytes) -> bytes:
        spec = COMMANDS.get(cmd)
        _check(spec is not None and self.firmware_major >= spec.min_firmware, E_INVALID_COMMAND)
        assert spec is not None
        _check(ptype in (T_WRITE, T_READ), E_INVALID_COMMAND)
        size = spec.write_size if ptype == T_WRITE else spec.read_size
        _check(size is not None, E_INVALID_COMMAND)
        _check(size == -1 or len(payload) == size, E_PAYLOAD_SIZE)
        if self.fail_next is not None:
            code, self.fail_next = self.fail_next, None
            raise Refused(code)
        _check((ptype, cmd) not in self.refuse, self.refuse.get((ptype, cmd), E_UNKNOWN))
        reply = self._read_value(cmd, payload) if ptype == T_READ else b""
        if ptype == T_WRITE:
            self._handlers[cmd](payload)
        self.state.commands.append(cmd)
        return reply

    # --- reads -----------------------------------------------------------------------------
    def _read_value(self, cmd: int, payload: bytes) -> bytes:
        st = self.state
        if cmd == 0x0100:
            _check(payload[0] in VERSION_SELECT)
            text = {0x00: self.firmware, 0x10: "2.0.0", 0x20: "1.0.0"}[payload[0]]
            return text.encode("ascii") + b"\0"
        if cmd == 0x0101:
            return bytes([st.display_mode])
        if cmd == 0x0103:
            return bytes([st.test_pattern])
        if cmd == 0x0104:
            return struct.pack("<HHH", *st.led_current)
        if cmd == 0x0404:
            _check(bool(st.trigger_out), E_NOT_INITIALISED)
            t = st.trigger_out
            return struct.pack("<BBBII", t["enable"], t["source"], t["polarity"], t["delay_us"],
                               t["width_us"])
        _check(bool(st.sequence) and st.sequence_command == cmd, E_NOT_INITIALISED)
        s = st.sequence
        fields = (s["bit_depth"], s["count"], s["inverted"], s["trigger"], s["delay_us"],
                  s["period_us"], s["exposure_us"], s["led"])
        if cmd == 0x0400:
            return struct.pack("<BBBBIIIB", *fields)
        return struct.pack("<BHBBIIIBB", *fields, s["play_mode"])

    # --- writes, one per row of the command table ------------------------------------------
    def _display_mode(self, payload: bytes) -> None:
        _check(payload[0] in DISPLAY_MODES)
        self.state.display_mode = payload[0]
        if payload[0] != 0x04:
            self.state.running = False

    def _test_pattern(self, payload: bytes) -> None:
        _check(payload[0] <= LAST_TEST_PATTERN)
        self.state.test_pattern = payload[0]

    def _led_current(self, payload: bytes) -> None:
        red, green, blue = struct.unpack("<HHH", payload)
        _check(max(red, green, blue) <= LED_CURRENT_MAX)
        self.state.led_current = (red, green, blue)

    def _sequence_legacy(self, payload: bytes) -> None:
        bits, count, inverted, trigger, delay_us, period_us, exposure_us, led = struct.unpack(
            "<BBBBIIIB", payload)
        _check(1 <= count <= 96)
        self._set_sequence(0x0400, bits, count, inverted, trigger, delay_us, period_us,
                           exposure_us, led, None)

    def _sequence_extended(self, payload: bytes) -> None:
        fields = struct.unpack("<BHBBIIIBB", payload)
        bits, count, inverted, trigger, delay_us, period_us, exposure_us, led, play = fields
        _check(1 <= count <= 1000 and play <= 1)
        self._set_sequence(0x0480, bits, count, inverted, trigger, delay_us, period_us,
                           exposure_us, led, play)

    def _set_sequence(self, cmd: int, bits: int, count: int, inverted: int, trigger: int,
                      delay_us: int, period_us: int, exposure_us: int, led: int,
                      play_mode: int | None) -> None:
        _check(1 <= bits <= 8 and inverted <= 1 and (not inverted or bits == 1))
        _check(trigger <= 0x06 and led <= 2 and exposure_us > 0)
        _check(trigger != 0x01 or period_us >= exposure_us)  # auto: the period holds the exposure
        st = self.state
        _check(not st.running, E_BUSY)  # stop the sequence before changing it
        old = st.sequence
        if (old.get("bit_depth"), old.get("count")) != (bits, count):
            st.patterns = {}  # new frame-memory layout: uploaded patterns are void
        st.sequence = {"bit_depth": bits, "count": count, "inverted": inverted,
                       "trigger": trigger, "delay_us": delay_us, "period_us": period_us,
                       "exposure_us": exposure_us, "led": led}
        if play_mode is not None:
            st.sequence["play_mode"] = play_mode
        st.sequence_command = cmd

    def _pattern(self, payload: bytes) -> None:
        st = self.state
        _check(len(payload) >= 2, E_PAYLOAD_SIZE)
        _check(bool(st.sequence), E_NOT_INITIALISED)
        bits, index = st.sequence["bit_depth"], payload[0]
        _check(index < min(st.sequence["count"], BIT_PLANES // bits))
        img = decode_bmp(payload[1:])
        _check(img.shape == (HEIGHT, WIDTH))
        low = np.uint8((1 << bits) - 1)
        if self.strict_levels:
            _check(int(img.max()) <= int(low))
        st.patterns[index] = img & low  # the DMD shows the least significant bits

    def _start_stop(self, payload: bytes) -> None:
        st = self.state
        _check(payload[0] in (0, 1))
        if payload[0] == 1:
            _check(st.display_mode == 0x04 and bool(st.sequence), E_NOT_INITIALISED)
            _check(all(i in st.patterns for i in range(st.sequence["count"])), E_NOT_FOUND)
            st.shown = 0
        st.running = payload[0] == 1

    def _advance(self, payload: bytes) -> None:
        st = self.state
        _check(st.running and st.sequence.get("trigger") == 0x00, E_NOT_INITIALISED)
        st.advances += 1
        st.shown = (st.shown + 1) % st.sequence["count"]

    def _trigger_out(self, payload: bytes) -> None:
        enable, source, polarity, delay_us, width_us = struct.unpack("<BBBII", payload)
        _check(enable <= 1 and polarity <= 1 and width_us > 0)
        self.state.trigger_out = {"enable": enable, "source": source, "polarity": polarity,
                                  "delay_us": delay_us, "width_us": width_us}

    def _display_pattern(self, payload: bytes) -> None:
        (index,) = struct.unpack("<H", payload)
        _check(index in self.state.patterns, E_NOT_FOUND)
        self.state.shown = index

    def describe(self) -> dict[str, Any]:
        st = self.state
        return {"port": self.port, "firmware": self.firmware, "mode": st.display_mode,
                "running": st.running, "patterns": sorted(st.patterns)}
