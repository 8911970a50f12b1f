"""``fringescope serve``: the live instrument with its web page and REST API."""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("serve", help="run the instrument's web service (simulator by default)")
    p.add_argument("--host", default=None, help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="TCP port (default 8000)")
    p.add_argument("--config", default=None, metavar="FILE", help="TOML settings file")
    p.add_argument("--data-dir", default=None, help="folder for calibrations and recordings")
    p.add_argument("--insecure", action="store_true", default=None,
                   help="allow binding beyond loopback without a token (see the security notes)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from app.config import load_settings
    from app.main import create_app

    settings = load_settings(
        args.config, host=args.host, port=args.port, data_dir=args.data_dir, insecure=args.insecure
    )
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")
    return 0
