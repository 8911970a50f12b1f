"""The LED/trigger controller over a serial port (protocol: hardware/PROTOCOL.md).

:class:`SerialLink` is one open port speaking the line protocol (thread-safe,
errors mapped to the device error family); :class:`SerialController` is the
:class:`~app.devices.base.Controller` built on it: exclusive open, post-open reset
wait, identify + version check, a supervisor thread that sends heartbeats and,
when the port disappears, reconnects with backoff (a ``usb:VID:PID[:SERIAL]``
port is looked up again by its USB identity; a path or symlink is simply retried).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import serial
from serial.tools import list_ports

from app.devices.base import Controller, DeviceState
from app.devices.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

try:  # tcflush on a vanished pty raises termios.error, which is not an OSError
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - Windows
    _TermiosError = OSError  # type: ignore[assignment,misc]

LINK_ERRORS = (serial.SerialException, OSError, _TermiosError)
PROTOCOL_MAJOR = 1
IDN_PREFIX = "FRINGESCOPE,LEDCTRL,"
BOOT_BANNER = b"# FRINGESCOPE LEDCTRL ready"
LED_CODES = {"red": "R", "green": "G", "blue": "B"}


class ControllerError(ProtocolError):
    """An ``ERR <code> <message>`` reply; ``code`` is the protocol's error code."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"controller refused: ERR {code} {message}")
        self.code = code


def parse_usb_spec(spec: str) -> tuple[int, int, str | None] | None:
    """``(vid, pid, serial or None)`` for ``usb:VID:PID[:SERIAL]``, None for other port names."""
    if not spec:
        raise ValueError("port: empty; give a device path, a pyserial URL or usb:VID:PID[:SERIAL]")
    if not spec.lower().startswith("usb:"):
        return None
    parts = spec.split(":")[1:]
    if len(parts) not in (2, 3):
        raise ValueError(f"port: expected usb:VID:PID[:SERIAL], got {spec!r}")
    try:
        vid, pid = int(parts[0], 16), int(parts[1], 16)
    except ValueError:
        raise ValueError(f"port: VID and PID must be hexadecimal, got {spec!r}") from None
    return vid, pid, (parts[2] if len(parts) == 3 else None)


def resolve_port(spec: str, ports: Iterable[Any] | None = None) -> str:
    """Turn ``spec`` into something ``serial_for_url`` opens.

    ``usb:VID:PID[:SERIAL]`` (hex VID/PID) selects the port whose USB identity
    matches among ``ports`` (default: ``serial.tools.list_ports.comports()``);
    anything else (``/dev/ttyACM0``, ``COM3``, ``rfc2217://host:port``) is returned as is.
    """
    usb = parse_usb_spec(spec)
    if usb is None:
        return spec
    vid, pid, want_sn = usb
    candidates = [
        p for p in (list_ports.comports() if ports is None else ports)
        if p.vid == vid and p.pid == pid and (want_sn is None or p.serial_number == want_sn)
    ]
    if not candidates:
        raise DeviceNotFound(f"no serial port with USB id {spec[4:]}")
    if len(candidates) > 1 and want_sn is None:
        names = ", ".join(sorted(p.device for p in candidates))
        raise DeviceNotFound(f"several ports match {spec}: {names}; add the serial number")
    return str(candidates[0].device)


class SerialLink:
    """One open port: send a command line, return the reply data after ``OK``."""

    def __init__(self, url: str, *, baudrate: int = 115200, timeout_s: float = 0.5) -> None:
        self.url = url
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s,
                                               write_timeout=timeout_s, exclusive=True)
        except serial.SerialException as exc:
            text = str(exc)
            if "exclusive" in text.lower() or "lock" in text.lower():
                raise DeviceError(f"{url}: port busy (open in another program)") from None
            raise DeviceNotFound(f"{url}: cannot open ({text})") from None
        except (OSError, ValueError) as exc:
            raise DeviceNotFound(f"{url}: cannot open ({exc})") from None

    def wait_for_banner(self, timeout_s: float) -> bool:
        """Read notices until the boot banner (True) or ``timeout_s`` passes (False).

        A board that reboots on open announces itself when ready, so there is no need
        to sit out the whole worst-case reset time.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            try:
                while (left := deadline - time.monotonic()) > 0:
                    self._port.timeout = min(left, self.timeout_s)
                    if self._port.readline().strip() == BOOT_BANNER:
                        return True
            except LINK_ERRORS as exc:
                raise DeviceDisconnected(f"{self.url}: link lost ({exc})") from None
            finally:
                with contextlib.suppress(*LINK_ERRORS):
                    self._port.timeout = self.timeout_s
        return False

    def discard_input(self) -> None:
        with self._lock:
            try:
                self._port.reset_input_buffer()
            except LINK_ERRORS as exc:
                raise DeviceDisconnected(f"{self.url}: {exc}") from None

    def command(self, line: str) -> str:
        """Send ``line``; return the text after ``OK`` (``""`` if none).

        Raises DeviceTimeout (no reply in time), ControllerError (``ERR``),
        ProtocolError (garbage), DeviceDisconnected (port gone).
        """
        with self._lock:
            try:
                # a reply that came after an earlier timeout must not pass for this one's
                self._port.reset_input_buffer()
                self._port.write((line + "\n").encode("ascii"))
                deadline = time.monotonic() + self.timeout_s
                while True:
                    raw = self._port.readline()
                    if not raw.endswith(b"\n"):
                        raise DeviceTimeout(f"{self.url}: no reply to {line!r} within "
                                            f"{self.timeout_s:.2f} s")
                    reply: str = raw.decode("ascii", "replace").strip()
                    if reply and not reply.startswith("#"):
                        break
                    if time.monotonic() > deadline:
                        raise DeviceTimeout(f"{self.url}: no reply to {line!r} (only notices)")
            except LINK_ERRORS as exc:
                raise DeviceDisconnected(f"{self.url}: link lost ({exc})") from None
        if reply == "OK":
            return ""
        if reply.startswith("OK "):
            return reply[3:]
        if reply.startswith("ERR "):
            code, _, msg = reply[4:].partition(" ")
            try:
                raise ControllerError(int(code), msg)
            except ValueError:
                pass
        raise ProtocolError(f"{self.url}: unexpected reply {reply!r} to {line!r}")

    def close(self) -> None:
        with contextlib.suppress(*LINK_ERRORS):
            self._port.close()


class SerialController(Controller):
    """LED/trigger controller on ``port`` (path, pyserial URL or ``usb:VID:PID[:SERIAL]``).

    Args:
        reset_wait_s: longest wait after opening for boards that reboot on open (Arduino: ~2 s);
            the wait ends early when the firmware's boot banner arrives.
        timeout_s: reply timeout per command.
        watchdog_ms: device watchdog; heartbeats go out every ``watchdog_ms / 4``.
        auto_reconnect: reopen by itself after an unplug, retrying with backoff
            from ``backoff_s[0]`` doubling to ``backoff_s[1]``.
        trigger_mode: ``"INT"`` (controller times triggers) or ``"PASS"`` (projector trigger
            relayed).
        list_ports_fn: enumerates ports for ``usb:`` lookup (default ``list_ports.comports``).
    """

    def __init__(
        self, port: str, *, baudrate: int = 115200, reset_wait_s: float = 2.0,
        timeout_s: float = 0.5, watchdog_ms: int = 2000, auto_reconnect: bool = True,
        backoff_s: tuple[float, float] = (0.05, 0.5),
        trigger_mode: str = "INT", pulses_per_set: int = 16, name: str | None = None,
        list_ports_fn: Callable[[], Iterable[Any]] | None = None,
    ) -> None:
        super().__init__(name=name or f"SerialController({port})")
        parse_usb_spec(port)  # validates the spelling now, not at the first open
        if not 100 <= watchdog_ms <= 60000:
            raise ValueError(f"watchdog_ms: must be within 100–60000, got {watchdog_ms}")
        if trigger_mode not in ("INT", "PASS"):
            raise ValueError(f"trigger_mode: must be 'INT' or 'PASS', got {trigger_mode!r}")
        self.port, self.baudrate = port, baudrate
        self.reset_wait_s, self.timeout_s = reset_wait_s, timeout_s
        self.watchdog_ms, self.auto_reconnect = watchdog_ms, auto_reconnect
        self.backoff_s = backoff_s
        self.trigger_mode, self.frames_per_set = trigger_mode, pulses_per_set
        self.list_ports_fn = list_ports_fn
        self.identity = ""
        self.reconnects = 0
        self._link: SerialLink | None = None
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._want_armed = False

    # --- hooks ---------------------------------------------------------------------
    def _do_open(self) -> None:
        ports = self.list_ports_fn() if self.list_ports_fn is not None else None
        link = SerialLink(resolve_port(self.port, ports), baudrate=self.baudrate,
                          timeout_s=self.timeout_s)
        try:
            if self.reset_wait_s > 0:
                link.wait_for_banner(self.reset_wait_s)
            link.discard_input()
            ident = link.command("*IDN?")
            if not ident.startswith(IDN_PREFIX):
                raise ProtocolError(
                    f"{link.url}: not a Fringescope controller (*IDN? gave {ident!r})")
            version = link.command("VER?")
            if version.split(".")[0] != str(PROTOCOL_MAJOR):
                raise ProtocolError(
                    f"{link.url}: protocol {version}, driver speaks {PROTOCOL_MAJOR}.x")
            link.command(f"WDT {self.watchdog_ms}")
            link.command("DISARM")
            link.command(f"TMODE {self.trigger_mode}")
            link.command(f"TCNT {self.frames_per_set}")
            self._apply_led(link, self.led, self.led_current)
        except BaseException:
            link.close()
            raise
        self._link, self.identity = link, ident
        self._start_supervisor()

    def _do_close(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        try:  # lights off where the link allows; the firmware watchdog covers the rest
            link.command("DISARM")
            link.command("LED OFF")
        except DeviceError as exc:
            self.log.debug("lights-off on close failed: %s", exc)
        finally:
            link.close()

    def _do_identify(self) -> str:
        return self._require_link().command("*IDN?")

    def _do_set_led(self, led: str, current: float) -> None:
        self._apply_led(self._require_link(), led, current)

    def _do_arm(self, armed: bool) -> None:
        self._require_link().command("ARM" if armed else "DISARM")
        self._want_armed = armed

    def _do_heartbeat(self) -> None:
        self._require_link().command("HB")

    def _do_set_sequence_length(self, n_frames: int) -> None:
        self._require_link().command(f"TCNT {n_frames}")

    def status(self) -> dict[str, str]:
        """``STAT?`` parsed into a dict (led, cur, armed, mode, intlk, wdt, pulses)."""
        with self._lock:
            self._require(DeviceState.OPEN, DeviceState.RUNNING, action="read status")
            text = str(self._call("status", lambda: self._require_link().command("STAT?")))
        return dict(item.split("=", 1) for item in text.split() if "=" in item)

    def close(self) -> None:
        self._stop.set()
        thread = self._supervisor
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        self._supervisor = None
        self._want_armed = False
        super().close()

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "port": self.port, "identity": self.identity,
                "reconnects": self.reconnects}

    # --- internals -----------------------------------------------------------------
    def _require_link(self) -> SerialLink:
        if self._link is None:
            raise DeviceDisconnected("serial link is not open")
        return self._link

    @staticmethod
    def _apply_led(link: SerialLink, led: str, current: float) -> None:
        code = LED_CODES[led]
        link.command(f"CUR {code} {round(current * 1000)}")
        link.command(f"LED {code}")

    def _start_supervisor(self) -> None:
        if self._supervisor is not None and self._supervisor.is_alive():
            return
        self._stop.clear()
        self._supervisor = threading.Thread(target=self._supervise, name=f"{self.name}-heartbeat",
                                            daemon=True)
        self._supervisor.start()

    def _supervise(self) -> None:
        """Heartbeat while healthy; after a fault, reopen with exponential backoff."""
        period_s = self.watchdog_ms / 4000.0
        misses, backoff, next_try = 0, self.backoff_s[0], 0.0
        while not self._stop.wait(
                0.02 if self._state is DeviceState.FAULT and self.auto_reconnect else period_s):
            if not self._lock.acquire(timeout=period_s):
                continue  # a long command holds the link; it restarts the watchdog anyway
            try:
                if self._stop.is_set():
                    return
                if self._state in (DeviceState.OPEN, DeviceState.RUNNING):
                    try:
                        self._call("heartbeat", self._do_heartbeat)
                        misses, backoff = 0, self.backoff_s[0]
                    except DeviceTimeout:
                        misses += 1
                        if misses >= 3:  # alive port, silent device: treat as gone
                            self._fault("no reply to 3 heartbeats")
                    except DeviceError:
                        pass  # _call has moved a disconnect to FAULT
                    except Exception as exc:  # never let the supervisor die silently
                        self._fault(f"heartbeat failed unexpectedly ({exc!r})")
                elif (self._state is DeviceState.FAULT and self.auto_reconnect
                      and time.monotonic() >= next_try):
                    try:
                        self.open()
                        self.reconnects += 1
                        self.log.warning("reconnected to %s", self.port)
                        if self._want_armed:
                            self.arm()
                        misses, backoff = 0, self.backoff_s[0]
                    except Exception as exc:  # keep retrying whatever the port does meanwhile
                        self.log.debug("reconnect failed: %s", exc)
                        next_try = time.monotonic() + backoff
                        backoff = min(backoff * 2, self.backoff_s[1])
                elif self._state is DeviceState.CLOSED:
                    return
            finally:
                self._lock.release()

    def _fault(self, reason: str) -> None:
        link = self._link
        if link is not None:
            with contextlib.suppress(DeviceError):
                link.command("LED OFF")
        self._state = DeviceState.FAULT
        self.last_error = f"{self.name}: {reason}"
        self.log.warning("fault: %s", reason)
