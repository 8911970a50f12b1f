"""``fringescope serve``: the live instrument with its web page and REST API."""

from __future__ import annotations

import argparse
import socket
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("serve",
                              help="run the instrument's web service (simulator by default)")
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
    check_port_free("HTTP", settings.host, settings.port)
    if settings.igtl_port is not None:
        check_port_free("OpenIGTLink", settings.igtl_host, settings.igtl_port)
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info",
                **proxy_options(settings.trusted_proxies))
    return 0


def proxy_options(trusted_proxies: list[str]) -> dict[str, Any]:
    """uvicorn's forwarded-header options: believed from the configured proxies only (uvicorn
    alone would believe any peer on 127.0.0.1)."""
    if not trusted_proxies:
        return {"proxy_headers": False}
    return {"proxy_headers": True, "forwarded_allow_ips": list(trusted_proxies)}


def check_port_free(what: str, host: str, port: int) -> None:
    """Raise ``OSError`` with one readable line when ``host:port`` cannot be bound.

    Checked before the service starts so a taken port is one line and exit code 2, not the
    traceback of a failed ASGI lifespan; the bind uses SO_REUSEADDR as the servers do, so
    a port in TIME_WAIT is not mistaken for a taken one.
    """
    if port == 0:
        return
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise OSError(f"{what} port {port} on {host} is not available ({exc.strerror or exc}); "
                          f"stop the program using it or choose another port") from None
