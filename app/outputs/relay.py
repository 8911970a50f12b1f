"""FastAPI routes relaying the viser server under ``/viser/``: the browser needs one port.

viser (1.1.x) serves its client as one self-contained ``index.html`` and opens its
WebSocket at the page's own URL without the trailing slash (``/viser/`` → ``ws://…/viser``),
so nothing needs rewriting: HTTP GETs are forwarded as they are, and WebSockets at
``/viser`` and ``/viser/`` are relayed byte for byte in both directions, subprotocol
(viser's version check) included. When either side closes, the other is closed with the
same code and both relay tasks are cancelled and awaited.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import TYPE_CHECKING

import httpx
import websockets
import websockets.asyncio.client
from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from starlette.websockets import WebSocketDisconnect, WebSocketState
from websockets.typing import Subprotocol

if TYPE_CHECKING:
    from app.outputs.viewer import Viewer

log = logging.getLogger(__name__)

# Close codes an endpoint may send (1005/1006/1015 are reserved for "none received").
_SENDABLE = set(range(1000, 1004)) | set(range(1007, 1015)) | set(range(3000, 5000))
_FORWARD_RESPONSE_HEADERS = ("content-type", "content-encoding", "cache-control", "etag")


def _upstream_port(viewer: Viewer) -> int | None:
    try:
        return int(viewer.port)
    except RuntimeError:  # not started / stopped
        return None


def viewer_router(viewer: Viewer, prefix: str = "/viser") -> APIRouter:
    """Routes relaying ``viewer`` (an :class:`app.outputs.viewer.Viewer`) under ``prefix``.

    The port is read per request, so the viewer may be started after the app is built.
    """
    if not prefix.startswith("/") or prefix.endswith("/"):
        raise ValueError(f"prefix: must start and not end with '/', got {prefix!r}")
    router = APIRouter()

    @router.get(prefix, include_in_schema=False)
    async def viser_root() -> Response:
        # The trailing slash matters: viser derives its WebSocket URL from the page URL.
        return RedirectResponse(prefix + "/", status_code=307)

    @router.get(prefix + "/{path:path}", include_in_schema=False)
    async def viser_http(path: str, request: Request) -> Response:
        port = _upstream_port(viewer)
        if port is None:
            return Response("3-D viewer not running", status_code=503, media_type="text/plain")
        url = f"http://127.0.0.1:{port}/{path}"
        headers = {"accept-encoding": request.headers.get("accept-encoding", "identity")}
        if request.url.query:
            url += "?" + request.url.query
        try:
            async with (
                httpx.AsyncClient(timeout=10.0) as client,
                client.stream("GET", url, headers=headers) as upstream,
            ):
                # Raw (still gzip-encoded) bytes: the encoding header is forwarded with them.
                body = b"".join([chunk async for chunk in upstream.aiter_raw()])
        except httpx.HTTPError as exc:
            log.warning("viser relay: GET %s failed: %s", url, exc)
            return Response("3-D viewer unreachable", status_code=502, media_type="text/plain")
        out = {k: v for k, v in upstream.headers.items() if k.lower() in _FORWARD_RESPONSE_HEADERS}
        out.setdefault("cache-control", "no-cache")
        return Response(body, status_code=upstream.status_code, headers=out)

    async def viser_ws(websocket: WebSocket) -> None:
        await relay_websocket(websocket, viewer)

    router.add_api_websocket_route(prefix, viser_ws)
    router.add_api_websocket_route(prefix + "/", viser_ws)
    return router


async def _refuse(websocket: WebSocket, offered: list[Subprotocol], code: int, reason: str) -> None:
    # Accept, then close with a code and reason: a refused handshake would reach the
    # browser as a bare failure (and the viser client would just retry).
    await websocket.accept(subprotocol=offered[0] if offered else None)
    await websocket.close(code=code, reason=reason)


async def relay_websocket(websocket: WebSocket, viewer: Viewer) -> None:
    """Relay one browser WebSocket to the viser server until either side closes."""
    offered = [Subprotocol(p) for p in websocket.scope.get("subprotocols", [])]
    port = _upstream_port(viewer)
    if port is None:
        await _refuse(websocket, offered, 1013, "3-D viewer not running")
        return
    try:
        upstream = await websockets.asyncio.client.connect(
            f"ws://127.0.0.1:{port}/",
            subprotocols=offered or None,
            max_size=None,  # viser sends whole point clouds in one message
            compression=None,
            open_timeout=5.0,
            close_timeout=2.0,
            ping_interval=None,  # the browser side keeps the connection alive
        )
    except (OSError, TimeoutError, websockets.exceptions.InvalidHandshake) as exc:
        log.warning("viser relay: upstream connect failed: %s", exc)
        await _refuse(websocket, offered, 1011, "3-D viewer unreachable")
        return

    await websocket.accept(subprotocol=upstream.subprotocol)

    async def downstream() -> None:  # viser → browser
        async for message in upstream:
            if isinstance(message, bytes):
                await websocket.send_bytes(message)
            else:
                await websocket.send_text(message)

    async def upstream_pump() -> None:  # browser → viser
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            if message.get("bytes") is not None:
                await upstream.send(message["bytes"])
            elif message.get("text") is not None:
                await upstream.send(message["text"])

    tasks = [
        asyncio.create_task(downstream(), name="viser-relay-down"),
        asyncio.create_task(upstream_pump(), name="viser-relay-up"),
    ]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            err = task.exception()
            if err is not None and not isinstance(
                err, websockets.exceptions.ConnectionClosed | WebSocketDisconnect
            ):
                log.warning("viser relay: %s ended: %r", task.get_name(), err)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await upstream.close()
        code = upstream.close_code if upstream.close_code in _SENDABLE else 1000
        reason = upstream.close_reason or "" if code != 1000 else ""
        if (
            websocket.application_state == WebSocketState.CONNECTED
            and websocket.client_state == WebSocketState.CONNECTED
        ):
            with contextlib.suppress(RuntimeError, OSError):
                await websocket.close(code=code, reason=reason)
