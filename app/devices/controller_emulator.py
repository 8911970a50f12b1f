"""Emulator of the LED/trigger controller firmware (hardware/PROTOCOL.md) on a pty pair.

:class:`ControllerProtocol` is the firmware's state machine in Python (one line in,
one reply out, plus the watchdog); :class:`PtyControllerEmulator` serves it on the
master end of a pseudo-terminal so the real driver talks to a real serial device
node. A stable symlink (``link_path``) always points at the current slave; the
emulator can drop replies, answer late, or vanish (master closed, exactly what a
USB unplug looks like to pyserial) and reappear on a new pty with the link re-pointed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

PROTOCOL_VERSION = "1.0"
FIRMWARE_VERSION = "1.0.0-emu"
MAX_LINE = 63
CHANNELS = ("R", "G", "B")
DEFAULTS: dict[str, int | str] = {"mode": "INT", "period_us": 20000, "delay_us": 0,
                                  "width_us": 100, "count": 16, "wdt_ms": 2000}
# (command, low, high) of the numeric single-argument timing commands
_NUMERIC = {"TPER": ("period_us", 1000, 1_000_000), "TDLY": ("delay_us", 0, 100_000),
            "TWID": ("width_us", 10, 100_000), "TCNT": ("count", 0, 65535),
            "WDT": ("wdt_ms", 100, 60_000)}

log = logging.getLogger("fringescope.devices.controller_emulator")


class _Err(Exception):
    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


def _int_arg(text: str, lo: int, hi: int) -> int:
    try:
        value = int(text, 10)
    except ValueError:
        raise _Err(3, f"not a number: {text}") from None
    if not lo <= value <= hi:
        raise _Err(3, f"{value} outside {lo}-{hi}")
    return value


@dataclass
class ControllerProtocol:
    """The firmware's behaviour; ``clock`` is injectable so tests can step time."""

    serial: str = "EMU0001"
    version: str = PROTOCOL_VERSION
    clock: object = time.monotonic
    led: str = "OFF"
    currents: dict[str, int] = field(default_factory=lambda: dict.fromkeys(CHANNELS, 0))
    armed: bool = False
    interlock_open: bool = False
    tripped: bool = False
    settings: dict[str, int | str] = field(default_factory=lambda: dict(DEFAULTS))
    notices: list[str] = field(default_factory=list)
    log: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._last_ok = self._now()
        self._arm_time = 0.0
        self._pass_pulses = 0
        # count of the last armed period, kept after DISARM like the firmware
        self._frozen_pulses = 0

    def _now(self) -> float:
        return float(self.clock())  # type: ignore[operator]

    # --- inputs besides the serial line -------------------------------------------
    def set_interlock(self, is_open: bool) -> None:
        if is_open and not self.interlock_open:
            self._disarm()
            self.led = "OFF"
            self.notices.append("# INTERLOCK open")
        elif not is_open and self.interlock_open:
            self.notices.append("# INTERLOCK closed")
        self.interlock_open = is_open

    def pulses(self) -> int:
        """Camera pulses since the last ARM (frozen when disarmed)."""
        if not self.armed:
            return self._frozen_pulses
        if self.settings["mode"] == "PASS":
            return self._pass_pulses
        n = int((self._now() - self._arm_time) * 1e6 // int(self.settings["period_us"])) + 1
        count = int(self.settings["count"])
        return min(n, count) if count else n

    def _disarm(self) -> None:
        if self.armed:
            self._frozen_pulses = self.pulses()
        self.armed = False

    def tick(self) -> None:
        """Watchdog: lights off and disarm when nothing arrived within WDT ms."""
        active = self.armed or self.led != "OFF"
        if active and self._now() - self._last_ok > int(self.settings["wdt_ms"]) / 1000.0:
            self._disarm()
            self.led, self.tripped = "OFF", True
            self.notices.append("# WATCHDOG tripped")

    def reset(self) -> None:
        self._disarm()
        self.led, self.tripped, self._frozen_pulses = "OFF", False, 0
        self.currents = dict.fromkeys(CHANNELS, 0)
        self.settings = dict(DEFAULTS)

    # --- the serial line ---------------------------------------------------------
    def handle_line(self, line: str) -> str:
        """Reply (without newline) to one received line (without newline).

        Like the firmware's loop (serial first, then safety), a command that arrives
        late still counts; the watchdog is checked by :meth:`tick` afterwards.
        """
        line = line.rstrip("\r")
        self.log.append(line)
        if len(line) > MAX_LINE:
            return "ERR 6 line too long"
        words = line.split()
        if not words:
            return "ERR 1 empty line"
        try:
            reply = self._dispatch(words[0], words[1:])
        except _Err as exc:
            return f"ERR {exc.code} {exc}"
        self._last_ok = self._now()
        return "OK" if not reply else f"OK {reply}"

    def _dispatch(self, cmd: str, args: list[str]) -> str:
        def nargs(n: int) -> None:
            if len(args) != n:
                raise _Err(2, f"{cmd} takes {n} argument(s)")

        def channel(text: str) -> str:
            if text not in CHANNELS:
                raise _Err(3, f"channel must be R, G or B: {text}")
            return text

        if cmd == "*IDN?":
            nargs(0)
            return f"FRINGESCOPE,LEDCTRL,{self.serial},{FIRMWARE_VERSION}"
        if cmd == "VER?":
            nargs(0)
            return self.version
        if cmd == "*RST":
            nargs(0)
            self.reset()
            return ""
        if cmd == "LED":
            nargs(1)
            if args[0] == "OFF":
                self.led = "OFF"
                return ""
            ch = channel(args[0])
            if self.interlock_open:
                raise _Err(4, "interlock open")
            self.led, self.tripped = ch, False
            return ""
        if cmd == "LED?":
            nargs(0)
            return self.led
        if cmd == "CUR":
            nargs(2)
            self.currents[channel(args[0])] = _int_arg(args[1], 0, 1000)
            return ""
        if cmd == "CUR?":
            nargs(1)
            return str(self.currents[channel(args[0])])
        if cmd == "TMODE" or cmd in _NUMERIC and cmd != "WDT":
            nargs(1)
            if self.armed:
                raise _Err(7, "disarm first")
            if cmd == "TMODE":
                if args[0] not in ("INT", "PASS"):
                    raise _Err(3, f"mode must be INT or PASS: {args[0]}")
                self.settings["mode"] = args[0]
            else:
                key, lo, hi = _NUMERIC[cmd]
                self.settings[key] = _int_arg(args[0], lo, hi)
            return ""
        if cmd == "WDT":
            nargs(1)
            self.settings["wdt_ms"] = _int_arg(args[0], 100, 60_000)
            return ""
        if cmd == "WDT?":
            nargs(0)
            return str(self.settings["wdt_ms"])
        if cmd == "ARM":
            nargs(0)
            if self.interlock_open:
                raise _Err(4, "interlock open")
            if self.tripped:
                raise _Err(5, "watchdog tripped; send LED to re-enable")
            self.armed, self._arm_time = True, self._now()
            self._pass_pulses, self._frozen_pulses = 0, 0
            return ""
        if cmd == "DISARM":
            nargs(0)
            self._disarm()
            return ""
        if cmd == "HB":
            nargs(0)
            return ""
        if cmd == "STAT?":
            nargs(0)
            cur = "/".join(str(self.currents[c]) for c in CHANNELS)
            intlk = "open" if self.interlock_open else "closed"
            return (f"led={self.led} cur={cur} armed={int(self.armed)} "
                    f"mode={self.settings['mode']} intlk={intlk} "
                    f"wdt={'tripped' if self.tripped else 'ok'} pulses={self.pulses()}")
        raise _Err(1, f"unknown command {cmd}")


class PtyControllerEmulator:
    """Serve :class:`ControllerProtocol` on a pty; ``link_path`` follows the current slave.

    Fault knobs (change any time): ``drop_rate`` (fraction of replies never sent),
    ``reply_delay_s`` (answer late), :meth:`vanish` / :meth:`reappear` (unplug/replug);
    ``auto_reset_s`` emulates the reboot-on-open of Arduino boards.
    """

    def __init__(
        self, link_path: str | os.PathLike[str] | None = None, *,
        protocol: ControllerProtocol | None = None, drop_rate: float = 0.0,
        reply_delay_s: float = 0.0, banner: bool = True, seed: int | None = None,
        auto_reset_s: float = 0.0,
    ) -> None:
        self.protocol = protocol or ControllerProtocol()
        self.link_path = Path(link_path) if link_path is not None else None
        self.drop_rate = drop_rate
        self.reply_delay_s = reply_delay_s
        self.banner = banner
        # > 0: like an Arduino, reboot whenever the host opens the port (silent for this long,
        # then the banner); the emulator then holds no slave fd, so it can see opens and closes
        self.auto_reset_s = auto_reset_s
        self._rng = random.Random(seed)
        self._master = self._slave = -1
        self.slave_name = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fd_lock = threading.Lock()

    @property
    def port(self) -> str:
        """What a driver should open: the symlink if configured, else the slave device."""
        return str(self.link_path) if self.link_path is not None else self.slave_name

    @property
    def present(self) -> bool:
        return self._master >= 0

    def start(self) -> PtyControllerEmulator:
        self._open_pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="controller-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_pty()
        if self.link_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link_path.unlink()

    def __enter__(self) -> PtyControllerEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def vanish(self) -> None:
        """Unplug: close both pty ends (an open pyserial port now fails with EIO) and remove the
        link, as udev removes /dev/ttyACM0 — so nobody reopens a recycled /dev/pts number
        meanwhile."""
        self._close_pty()
        if self.link_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link_path.unlink()

    def reappear(self) -> None:
        """Replug: a fresh pty (new device name), symlink re-pointed, firmware rebooted."""
        self.protocol.reset()
        self._open_pty()

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: bytes pass as on a UART
        self.slave_name = os.ttyname(slave)
        if self.auto_reset_s > 0:
            os.close(slave)  # hung-up master = no host; the raw settings stay with the pty
            slave = -1
        with self._fd_lock:
            self._master, self._slave = master, slave  # a held slave keeps master reads from EIO
        if self.link_path is not None:
            tmp = self.link_path.with_name(self.link_path.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, self.link_path)
        if self.banner and self.auto_reset_s <= 0:
            self._write("# FRINGESCOPE LEDCTRL ready")
        log.info("controller emulator on %s", self.port)

    def _reboot(self) -> None:
        """DTR reset on open: state lost, deaf while booting, then the banner."""
        self.protocol.reset()
        self._stop.wait(self.auto_reset_s)
        with self._fd_lock, contextlib.suppress(OSError):
            if self._master >= 0:
                while select.select([self._master], [], [], 0)[0] and os.read(self._master, 1024):
                    pass  # bytes sent to a booting board are lost
        if self.banner:
            self._write("# FRINGESCOPE LEDCTRL ready")

    def _close_pty(self) -> None:
        with self._fd_lock:
            for fd in (self._master, self._slave):
                if fd >= 0:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self._master = self._slave = -1

    def _write(self, line: str) -> None:
        with self._fd_lock:
            if self._master >= 0:
                with contextlib.suppress(OSError):
                    os.write(self._master, (line + "\n").encode("ascii"))

    def _serve(self) -> None:
        buf, host_open = b"", False
        while not self._stop.is_set():
            master = self._master
            if master < 0:
                buf, host_open = b"", False
                time.sleep(0.02)
                continue
            try:
                poller = select.poll()
                poller.register(master, select.POLLIN)
                events = poller.poll(20)
                hung_up = bool(events) and bool(events[0][1] & select.POLLHUP)
                chunk = os.read(master, 1024) if events and not hung_up else b""
            except (OSError, ValueError):  # closed under us by vanish()
                time.sleep(0.01)
                continue
            if hung_up:  # no host has the port open (auto-reset mode only)
                host_open = False
                time.sleep(0.01)
                continue
            if self.auto_reset_s > 0 and not host_open:
                host_open = True
                self._reboot()
                continue
            buf += chunk
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                reply = self.protocol.handle_line(raw.decode("ascii", "replace"))
                if self.drop_rate and self._rng.random() < self.drop_rate:
                    continue
                if self.reply_delay_s:
                    time.sleep(self.reply_delay_s)
                self._write(reply)
            if len(buf) > MAX_LINE:  # overlong: keep only "too long" until its newline (ERR 6 then)
                buf = b"?" * (MAX_LINE + 1)
            self.protocol.tick()
            while self.protocol.notices:
                self._write(self.protocol.notices.pop(0))
