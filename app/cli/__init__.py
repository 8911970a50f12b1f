"""The ``fringescope`` command line.

Each module in this package that defines ``register(subparsers)`` adds one
subcommand; the parser sets ``func`` to the handler, which returns an exit code.
Bad input (``ValueError``, a device error, a missing file) is one line on stderr
and exit code 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
from collections.abc import Sequence

from app import __version__
from app.core.jit import configure_numerics


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fringescope",
        description="Structured-illumination 3-D laparoscope: fringe images to metric depth.",
    )
    parser.add_argument("--version", action="version", version=f"fringescope {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    configure_numerics()  # before the commands import numpy and numba (app/core/jit.py)
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from app.core.errors import DomainError
    from app.devices.errors import DeviceError

    try:
        return int(args.func(args) or 0)
    except (ValueError, DomainError, DeviceError, OSError) as exc:
        print(f"fringescope {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
