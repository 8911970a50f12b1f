"""``fringescope emulate controller|lightcrafter``: serve a device emulator until Ctrl-C.

``controller`` prints the serial device path to open (a pty; ``--link`` makes a
stable symlink), ``lightcrafter`` prints ``host:port`` of the fake projector.
"""

from __future__ import annotations

import argparse
import threading
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "emulate", help="serve a hardware emulator (serial controller, LightCrafter)")
    sub = parser.add_subparsers(dest="device", metavar="DEVICE", required=True)
    ctl = sub.add_parser("controller", help="LED/trigger controller on a pseudo-terminal")
    ctl.add_argument("--link",
                     help="also make this symlink to the pty (stable across --vanish-every)")
    ctl.add_argument("--serial", default="EMU0001", help="serial number reported by *IDN?")
    ctl.add_argument("--drop-rate", type=float, default=0.0,
                     help="fraction of replies never sent (0-1)")
    ctl.add_argument("--delay-ms", type=float, default=0.0, help="answer every command this late")
    ctl.add_argument("--vanish-every", type=float, default=0.0, metavar="S",
                     help="unplug every S seconds and come back 1 s later on a new pty (0: never)")
    ctl.set_defaults(func=run_controller)
    lcr = sub.add_parser("lightcrafter", help="fake LightCrafter 3000 TCP server")
    lcr.add_argument("--host", default="127.0.0.1")
    lcr.add_argument("--port", type=int, default=21845)
    lcr.add_argument("--firmware", default="5.0.0",
                     help="DM365 version string; below 3.0 only the legacy 0x0400 sequence")
    lcr.add_argument("--lenient-levels", action="store_true",
                     help="take pattern levels above the bit depth (shown wrapped, as the device)")
    lcr.set_defaults(func=run_lightcrafter)


def _wait(stop: threading.Event, seconds: float) -> bool:
    """Sleep until ``stop`` (Ctrl-C arrives as KeyboardInterrupt in the main thread)."""
    return stop.wait(seconds if seconds > 0 else 3600.0)


def run_controller(args: argparse.Namespace) -> int:
    from app.devices.controller_emulator import ControllerProtocol, PtyControllerEmulator

    if not 0.0 <= args.drop_rate <= 1.0:
        raise ValueError(f"--drop-rate: must be within 0-1, got {args.drop_rate}")
    if args.delay_ms < 0 or args.vanish_every < 0:
        raise ValueError("--delay-ms/--vanish-every: must be >= 0")
    emu = PtyControllerEmulator(args.link, protocol=ControllerProtocol(serial=args.serial),
                                drop_rate=args.drop_rate, reply_delay_s=args.delay_ms / 1000.0)
    emu.start()
    stop = threading.Event()
    try:  # Ctrl-C may come as soon as the path is printed
        print(emu.port, flush=True)
        while not _wait(stop, args.vanish_every):
            if args.vanish_every > 0:
                emu.vanish()
                print("vanished", flush=True)
                _wait(stop, 1.0)
                emu.reappear()
                print(emu.port, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    return 0


def run_lightcrafter(args: argparse.Namespace) -> int:
    from app.devices.lightcrafter_emulator import LightCrafterEmulator

    emu = LightCrafterEmulator(args.host, args.port, firmware=args.firmware,
                               strict_levels=not args.lenient_levels).start()
    try:
        print(f"{emu.host}:{emu.port}", flush=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    return 0
