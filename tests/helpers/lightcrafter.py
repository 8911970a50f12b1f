"""Raw exchanges with the LightCrafter emulator, for tests that check packets byte by byte."""

from __future__ import annotations

import socket

from app.devices.lightcrafter_emulator import LightCrafterEmulator


def raw_exchange(emu: LightCrafterEmulator, data: bytes) -> bytes:
    """Send raw bytes on a fresh connection, return the raw reply packet."""
    with socket.create_connection((emu.host, emu.port), timeout=2) as s:
        s.sendall(data)
        head = s.recv(6, socket.MSG_WAITALL)
        return head + s.recv(head[4] + 256 * head[5] + 1, socket.MSG_WAITALL)
