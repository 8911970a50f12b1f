"""``fringescope probe lightcrafter HOST``: the hardware bring-up checks of a DLP LightCrafter.

One line a step, ``ok`` or ``FAIL`` with the device's answer, so that a first session
with a real DLP3000 finds a protocol mismatch in minutes (README, "LightCrafter
bring-up"). Steps: the DM365 version (0x0100) and the sequence command it calls for; the
FPGA and MSP430 versions; status read-back (display mode 0x0101, LED current 0x0104); one
fringe pattern shown (0x0480 or 0x0400, 0x0401, 0x0404, 0x0402); each LED flashed in turn
and its current read
back; the trigger-output setting read back (the pulse itself is measured with the camera,
see the README). Exit 0 when every step passed, 1 when one failed, 2 for bad input or no
connection. The lights are off at the end.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

from app.devices.errors import DeviceError, ProtocolError

if TYPE_CHECKING:
    from app.devices.lightcrafter import LightCrafterClient


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("probe", help="bring-up checks of real hardware (LightCrafter)")
    sub = parser.add_subparsers(dest="device", metavar="DEVICE", required=True)
    lcr = sub.add_parser("lightcrafter", help="talk to a DLP LightCrafter 3000 step by step",
                         description=__doc__)
    lcr.add_argument("host", metavar="HOST", help="the projector's address (USB-RNDIS: "
                     "192.168.1.100)")
    lcr.add_argument("--port", type=int, default=21845, help="TCP port (default 21845 = 0x5555)")
    lcr.add_argument("--timeout-s", type=float, default=3.0, help="reply timeout per packet")
    lcr.add_argument("--led-current", type=int, default=100, metavar="CODE",
                     help="LED current code for the flashes, 0-274 (274 ≈ 633 mA, the "
                     "continuous limit without active cooling; default 100)")
    lcr.add_argument("--show-s", type=float, default=3.0, help="seconds the pattern is shown")
    lcr.add_argument("--flash-s", type=float, default=1.0, help="seconds each LED is lit")
    lcr.set_defaults(func=run_lightcrafter)


@dataclass
class StepResult:
    name: str
    ok: bool
    detail: str


class ProbeSteps:
    """Run named steps, print one line each; a protocol error fails the step, not the probe."""

    def __init__(self, out: Callable[[str], None]) -> None:
        self.out, self.results = out, list[StepResult]()

    def run(self, name: str, step: Callable[[], str]) -> bool:

        try:
            detail, ok = step(), True
        except (ProtocolError, _Mismatch) as exc:
            detail, ok = str(exc), False
        self.results.append(StepResult(name, ok, detail))
        self.out(f"{'ok  ' if ok else 'FAIL'} {name}: {detail}")
        return ok


class _Mismatch(Exception):
    """A read-back that differs from what was written."""


def _check_arguments(args: argparse.Namespace) -> None:
    if not 0 <= args.led_current <= 274:
        raise ValueError(f"--led-current: need a code within 0-274, got {args.led_current}")
    if args.show_s < 0 or args.flash_s < 0 or args.timeout_s <= 0:
        raise ValueError("--show-s/--flash-s: must be >= 0, --timeout-s > 0")
    if not 0 < args.port < 65536:
        raise ValueError(f"--port: need 1-65535, got {args.port}")


def run_lightcrafter(args: argparse.Namespace, stdout: TextIO | None = None) -> int:
    import sys

    from app.devices.lightcrafter import LightCrafterClient

    _check_arguments(args)
    stream = stdout or sys.stdout
    client = LightCrafterClient(args.host, args.port, timeout_s=args.timeout_s)
    client.connect()  # DeviceNotFound / DeviceTimeout: one line, exit 2
    steps = ProbeSteps(lambda line: print(line, file=stream, flush=True))
    try:
        probe_lightcrafter(client, steps, led_current=args.led_current, show_s=args.show_s,
                           flash_s=args.flash_s)
    finally:
        try:  # lights off, sequence stopped, whatever happened
            client.start_sequence(False)
            client.set_led_current(0, 0, 0)
        except DeviceError as exc:
            print(f"FAIL lights off: {exc}", file=stream)
        client.close()
    failed = [r.name for r in steps.results if not r.ok]
    print(f"{len(steps.results) - len(failed)}/{len(steps.results)} steps ok"
          + (f"; failed: {', '.join(failed)}" if failed else ""), file=stream)
    return 1 if failed else 0


def probe_lightcrafter(client: LightCrafterClient, steps: ProbeSteps, *, led_current: int,
                       show_s: float, flash_s: float) -> None:
    """The bring-up steps on a connected :class:`LightCrafterClient`."""
    from app.core.schedule import PatternSchedule
    from app.devices.lightcrafter import (
        EXTENDED_SEQUENCE_FIRMWARE,
        LED_SELECT,
        MODE_PATTERN_SEQUENCE,
        TRIG_AUTO,
        VERSION_DM365,
        VERSION_FPGA,
        VERSION_MSP430,
        encode_bmp,
        firmware_major,
        quantise_levels,
    )
    from app.recon.patterns import generate_patterns

    exposure_us, period_us, bits = 20000, 22000, 6  # 6 bits: the 16-pattern schedule's depth
    trigger = {"enable": 1, "source": 0, "polarity": 0, "delay_us": 0, "width_us": 100}
    extended = [True]

    def version() -> str:
        dm365 = client.version(VERSION_DM365)
        major = firmware_major(dm365)
        extended[0] = major is None or major >= EXTENDED_SEQUENCE_FIRMWARE
        command = "0x0480" if extended[0] else "0x0400 (legacy)"
        return f"DM365 {dm365!r}; sequence command {command}"

    def other_versions() -> str:
        fpga, msp430 = client.version(VERSION_FPGA), client.version(VERSION_MSP430)
        return f"FPGA {fpga!r}, MSP430 {msp430!r}"

    def status() -> str:
        mode, currents = client.display_mode(), client.led_current()
        return f"display mode {mode}, LED current R/G/B {currents}"

    def pattern() -> str:
        schedule = PatternSchedule()
        image = generate_patterns(schedule)[schedule.frame_index(1, 0)]  # 4 fringes, shift 0
        client.start_sequence(False)
        client.set_display_mode(MODE_PATTERN_SEQUENCE)
        client.set_led_current(0, led_current, 0)
        client.set_sequence(bit_depth=bits, count=1, trigger=TRIG_AUTO, exposure_us=exposure_us,
                            period_us=period_us, led=LED_SELECT["green"], extended=extended[0])
        client.define_pattern(0, encode_bmp(quantise_levels(image, bits), 8))
        client.set_trigger_out(enable=True, source=trigger["source"], delay_us=0,
                               width_us=trigger["width_us"])
        client.start_sequence(True)
        time.sleep(show_s)
        return (f"look: {schedule.frequencies[1]} vertical fringes, green, for {show_s:g} s "
                f"(levels 0-{2**bits - 1} at {bits} bits; dim fringes: the device reads the "
                f"upper bits; {exposure_us} µs exposure, {period_us} µs period)")

    def leds() -> str:
        seen = []
        for name, index in LED_SELECT.items():
            client.start_sequence(False)
            client.set_sequence(bit_depth=bits, count=1, trigger=TRIG_AUTO,
                                exposure_us=exposure_us, period_us=period_us, led=index,
                                extended=extended[0])
            currents = [0, 0, 0]
            currents[index] = led_current
            client.set_led_current(*currents)
            client.start_sequence(True)
            time.sleep(flash_s)
            back = client.led_current()
            if list(back) != currents:
                raise _Mismatch(f"{name}: wrote LED current {tuple(currents)}, read {back}")
            seen.append(name)
        client.start_sequence(False)
        return f"look: {', '.join(seen)} lit {flash_s:g} s each at code {led_current}; read back"

    def trigger_out() -> str:
        back = client.trigger_out()
        if back != trigger:
            raise _Mismatch(f"wrote {trigger}, read {back}")
        return (f"enabled, positive, {trigger['width_us']} µs pulse every {period_us} µs: "
                "measure it with the camera (README)")

    if not steps.run("version", version):
        return
    steps.run("FPGA and MSP430 versions", other_versions)
    steps.run("status", status)
    if steps.run("pattern", pattern):
        steps.run("trigger output", trigger_out)
    steps.run("LEDs", leds)
