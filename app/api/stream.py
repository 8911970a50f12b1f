"""Live depth colormap for the page: WebSocket (binary JPEG per result) and MJPEG."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

from fastapi import APIRouter, Depends, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from app.api.deps import get_instrument
from app.api.errors import COMMON, R422
from app.core.errors import InvalidRequest
from app.outputs import encoding
from app.service.instrument import Instrument
from app.service.reconstruction import LiveResult

router = APIRouter(prefix="/api/stream", tags=["stream"])

WAIT_S = 0.5


def _jpeg(res: LiveResult, rng: tuple[float, float]) -> bytes:
    return res.cached(("jpeg", rng), lambda: encoding.depth_color_jpeg(res.depth, rng))


async def _frames(inst: Instrument, rng: tuple[float, float]) -> AsyncIterator[tuple[LiveResult, bytes]]:
    """Each new result once, encoded (shared between clients), until shutdown."""
    seq = 0
    while not inst.results.closed:
        res = await run_in_threadpool(inst.wait_result, seq, WAIT_S)
        if res is None:
            continue
        seq = res.seq
        yield res, await run_in_threadpool(_jpeg, res, rng)


@router.websocket("/depth")
async def depth_ws(
    websocket: WebSocket,
    min_mm: float | None = Query(None),
    max_mm: float | None = Query(None),
) -> None:
    """Sends every new depth colormap as one binary JPEG message, at the depth rate."""
    inst: Instrument | None = getattr(websocket.app.state, "instrument", None)
    try:
        rng = encoding.check_range_mm(min_mm, max_mm)
    except InvalidRequest as exc:
        await websocket.close(code=1008, reason=exc.detail[:120])
        return
    await websocket.accept()
    if inst is None:
        await websocket.close(code=1011, reason="instrument not started")
        return
    async def pump() -> None:
        async for _, data in _frames(inst, rng):
            await websocket.send_bytes(data)

    async def until_disconnect() -> None:
        # issue 7: notice a client leaving (or the server shutting down) even while no result
        # arrives — otherwise the handler waits forever and blocks uvicorn's graceful shutdown
        while (await websocket.receive())["type"] != "websocket.disconnect":
            pass

    tasks = {asyncio.ensure_future(pump()), asyncio.ensure_future(until_disconnect())}
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            if not task.cancelled() and isinstance(task.exception(), (WebSocketDisconnect, RuntimeError)):
                return  # the client went away
            task.result()
    finally:
        for task in tasks:
            task.cancel()


@router.get("/depth.mjpeg", responses={200: {"content": {"multipart/x-mixed-replace": {}}}, **R422, **COMMON})
async def depth_mjpeg(
    min_mm: float | None = Query(None, allow_inf_nan=False),
    max_mm: float | None = Query(None, allow_inf_nan=False),
    frames: int | None = Query(None, ge=1, description="end after this many images (default: never)"),
    inst: Instrument = Depends(get_instrument),
) -> StreamingResponse:
    """The same images as a ``multipart/x-mixed-replace`` MJPEG stream (an <img> can show it)."""
    rng = encoding.check_range_mm(min_mm, max_mm)

    async def body() -> AsyncIterator[bytes]:
        sent = 0
        async for _, data in _frames(inst, rng):
            yield (b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                   + str(len(data)).encode() + b"\r\n\r\n" + data + b"\r\n")
            sent += 1
            if frames is not None and sent >= frames:
                break
        yield b"--frame--\r\n"

    return StreamingResponse(body(), media_type="multipart/x-mixed-replace; boundary=frame",
                             headers={"Cache-Control": "no-store"})
