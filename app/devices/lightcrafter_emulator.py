"""A fake LightCrafter 3000: the DM365 TCP packet protocol, byte for byte, on a real socket.

Parses packets itself (not with the client's helpers, so a framing bug on one side
shows), checks checksums, payload sizes and multi-packet flags, answers write/read
responses, ``busy`` (``busy_next`` times) and error packets with the DLPU007 error
codes, keeps what was uploaded (decoded BMP patterns, sequence and trigger-out
settings, LED currents), and can be stopped and restarted on the same port to
look like an unplugged projector.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

log = logging.getLogger("fringescope.devices.lightcrafter_emulator")

WIDTH, HEIGHT = 608, 684
VERSIONS = {0x00: b"5.0.0 fringescope-emu\0", 0x10: b"2.0.0\0", 0x20: b"1.0.0\0"}
# command -> (allowed packet type, exact payload size or None for variable)
COMMANDS: dict[int, tuple[int, int | None]] = {
    0x0100: (0x04, 1), 0x0101: (0x02, 1), 0x0103: (0x02, 6), 0x0400: (0x02, 17), 0x0401: (0x02, None),
    0x0402: (0x02, 1), 0x0403: (0x02, 0), 0x0404: (0x02, 10), 0x0405: (0x02, 2),
}
E_INVALID_COMMAND, E_INVALID_PARAMETER, E_NOT_INITIALISED = 0x02, 0x03, 0x07
E_OBJECT_NOT_FOUND, E_CHECKSUM, E_PACKET_FORMAT, E_CONTINUATION = 0x08, 0x09, 0x0A, 0x0B


class _Refuse(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def decode_bmp(data: bytes) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 grey levels of an uncompressed 1- or 8-bit palette BMP (raises _Refuse)."""
    if len(data) < 54 or data[:2] != b"BM":
        raise _Refuse(E_INVALID_PARAMETER)
    offset = struct.unpack_from("<I", data, 10)[0]
    _, w, h, _, bits, compression = struct.unpack_from("<IiiHHI", data, 14)
    if bits not in (1, 8) or compression != 0 or w <= 0 or h == 0:
        raise _Refuse(E_INVALID_PARAMETER)
    n_colours = struct.unpack_from("<I", data, 46)[0] or (1 << bits)
    palette = np.frombuffer(data, np.uint8, n_colours * 4, 54).reshape(-1, 4)[:, 0]  # blue channel = grey
    stride = ((w * bits + 7) // 8 + 3) // 4 * 4
    if len(data) < offset + stride * abs(h):
        raise _Refuse(E_PACKET_FORMAT)
    rows = np.frombuffer(data, np.uint8, stride * abs(h), offset).reshape(abs(h), stride)
    idx = rows[:, :w] if bits == 8 else np.unpackbits(rows, axis=1)[:, :w]
    img = palette[idx]
    return img[::-1] if h > 0 else img


@dataclass
class LightCrafterState:
    display_mode: int = 0x00
    led_current: tuple[int, int, int] = (274, 274, 274)
    sequence: dict[str, int] = field(default_factory=dict)
    trigger_out: dict[str, int] = field(default_factory=dict)
    patterns: dict[int, npt.NDArray[np.uint8]] = field(default_factory=dict)
    running: bool = False
    shown: int = 0
    advances: int = 0
    commands: list[int] = field(default_factory=list)
    bytes_received: int = 0  # every packet byte the projector read (uploads are ~420 kB a pattern)


class LightCrafterEmulator:
    """Serve the protocol on ``host:port`` (port 0: pick a free one; see ``.port``).

    Faults: ``busy_next`` (answer that many packets with busy), ``fail_next`` (an error
    code for the next command), :meth:`stop` / :meth:`start` (unplug / replug).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host, self.port = host, port
        self.state = LightCrafterState()
        self.busy_next = 0
        self.fail_next: int | None = None
        self._server: socket.socket | None = None
        self._conns: set[socket.socket] = set()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    # --- lifecycle -------------------------------------------------------------------------
    def start(self) -> LightCrafterEmulator:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind((self.host, self.port))
        server.listen(4)
        self.port = server.getsockname()[1]
        self._server = server
        self.state = LightCrafterState()  # a power cycle forgets everything
        t = threading.Thread(target=self._accept, args=(server,), name="lightcrafter-emulator", daemon=True)
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
        pending: tuple[int, bytearray] | None = None  # multi-packet upload in progress
        try:
            while True:
                head = self._read(conn, 6)
                if head is None:
                    return
                ptype, cmd = head[0], (head[1] << 8) | head[2]
                flags, length = head[3], head[4] | (head[5] << 8)
                rest = self._read(conn, length + 1)
                if rest is None:
                    return
                payload, check = rest[:-1], rest[-1]
                self.state.bytes_received += len(head) + len(rest)
                if sum(head + payload) % 256 != check:
                    self._send(conn, 0x01, cmd, bytes([E_CHECKSUM]))
                    continue
                if self.busy_next > 0:
                    self.busy_next -= 1
                    self._send(conn, 0x00, cmd, b"")
                    continue
                try:
                    pending, reply = self._packet(ptype, cmd, flags, payload, pending)
                except _Refuse as exc:
                    pending = None
                    self._send(conn, 0x01, cmd, bytes([exc.code]))
                    continue
                self._send(conn, 0x05 if ptype == 0x04 else 0x03, cmd, reply)
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
        packet = bytes([ptype, cmd >> 8, cmd & 0xFF, 0x00, len(payload) & 0xFF, len(payload) >> 8]) + payload
        conn.sendall(packet + bytes([sum(packet) % 256]))

    def _packet(
        self, ptype: int, cmd: int, flags: int, payload: bytes, pending: tuple[int, bytearray] | None
    ) -> tuple[tuple[int, bytearray] | None, bytes]:
        """Reassemble multi-packet payloads; run the command when complete."""
        if flags not in (0, 1, 2, 3):
            raise _Refuse(E_PACKET_FORMAT)
        if flags in (2, 3) and (pending is None or pending[0] != cmd):
            raise _Refuse(E_CONTINUATION)
        if flags in (0, 1) and pending is not None:
            raise _Refuse(E_CONTINUATION)
        if flags == 1:
            return (cmd, bytearray(payload)), b""
        if flags == 2:
            assert pending is not None
            pending[1].extend(payload)
            return pending, b""
        if flags == 3:
            assert pending is not None
            payload = bytes(pending[1] + payload)
        return None, self._execute(ptype, cmd, payload)

    def _execute(self, ptype: int, cmd: int, payload: bytes) -> bytes:
        if cmd not in COMMANDS:
            raise _Refuse(E_INVALID_COMMAND)
        want_type, size = COMMANDS[cmd]
        if ptype != want_type:
            raise _Refuse(E_INVALID_COMMAND)
        if size is not None and len(payload) != size:
            raise _Refuse(E_PACKET_FORMAT)
        if self.fail_next is not None:
            code, self.fail_next = self.fail_next, None
            raise _Refuse(code)
        st = self.state
        st.commands.append(cmd)
        if cmd == 0x0100:
            if payload[0] not in VERSIONS:
                raise _Refuse(E_INVALID_PARAMETER)
            return VERSIONS[payload[0]]
        if cmd == 0x0101:
            if payload[0] not in (0x00, 0x01, 0x02, 0x04):
                raise _Refuse(E_INVALID_PARAMETER)
            st.display_mode = payload[0]
        elif cmd == 0x0103:
            cur = struct.unpack("<HHH", payload)
            if max(cur) > 1024:
                raise _Refuse(E_INVALID_PARAMETER)
            st.led_current = cur
        elif cmd == 0x0400:
            self._sequence(payload)
        elif cmd == 0x0401:
            if len(payload) < 2:
                raise _Refuse(E_PACKET_FORMAT)
            index = payload[0]
            limit = st.sequence.get("count", 96)
            img = decode_bmp(payload[1:])
            if index >= limit or img.shape != (HEIGHT, WIDTH):
                raise _Refuse(E_INVALID_PARAMETER)
            st.patterns[index] = img
        elif cmd == 0x0402:
            if payload[0] not in (0, 1):
                raise _Refuse(E_INVALID_PARAMETER)
            if payload[0] == 1 and (st.display_mode != 0x04 or not st.sequence):
                raise _Refuse(E_NOT_INITIALISED)
            if payload[0] == 1 and any(i not in st.patterns for i in range(st.sequence["count"])):
                raise _Refuse(E_OBJECT_NOT_FOUND)
            st.running = payload[0] == 1
        elif cmd == 0x0403:
            if not st.running:
                raise _Refuse(E_NOT_INITIALISED)
            st.advances += 1
            st.shown = (st.shown + 1) % st.sequence["count"]
        elif cmd == 0x0404:
            enable, falling, delay_us, width_us = struct.unpack("<BBII", payload)
            if enable > 1 or falling > 1 or width_us == 0:
                raise _Refuse(E_INVALID_PARAMETER)
            st.trigger_out = {"enable": enable, "falling": falling, "delay_us": delay_us, "width_us": width_us}
        elif cmd == 0x0405:
            (index,) = struct.unpack("<H", payload)
            if index not in st.patterns:
                raise _Refuse(E_OBJECT_NOT_FOUND)
            st.shown = index
        return b""

    def _sequence(self, payload: bytes) -> None:
        bits, count, inverted, trigger, delay_us, period_us, exposure_us, led = struct.unpack("<BBBBIIIB", payload)
        ok = (1 <= bits <= 8 and 1 <= count <= 96 // bits and inverted <= 1 and trigger <= 0x03
              and led <= 2 and exposure_us > 0 and (trigger != 0x01 or period_us >= exposure_us))
        if not ok:
            raise _Refuse(E_INVALID_PARAMETER)
        if self.state.running:
            raise _Refuse(E_NOT_INITIALISED)  # stop the sequence before changing it
        old = self.state.sequence
        if (old.get("bit_depth"), old.get("count")) != (bits, count):
            self.state.patterns = {}  # new frame-memory layout: uploaded patterns are void
        self.state.sequence = {"bit_depth": bits, "count": count, "inverted": inverted, "trigger": trigger,
                               "delay_us": delay_us, "period_us": period_us, "exposure_us": exposure_us, "led": led}

    def describe(self) -> dict[str, Any]:
        st = self.state
        return {"port": self.port, "mode": st.display_mode, "running": st.running, "patterns": sorted(st.patterns)}
