"""Live depth colormap for the page: WebSocket (binary JPEG per result) and MJPEG.

Streams hold no worker thread: one feed thread per app waits on the result slot and wakes
every stream on the event loop (:class:`ResultFeed`); the JPEG of a result is encoded once per
colour range in a pool of its own (:data:`ENCODE_THREADS` threads) and shared by all streams.
So however many streams run, the worker threads stay free for control and status. A client
(its address; behind a trusted proxy the forwarded one) may hold at most
``max_streams_per_client`` streams at once; more are refused with 429.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated

from fastapi import (
    APIRouter,
    Depends,
    HTTPException,
    Query,
    Request,
    WebSocket,
    WebSocketDisconnect,
)
from fastapi.responses import JSONResponse, StreamingResponse
from starlette.types import Receive, Scope, Send

from app.api.errors import COMMON, R422, Responses
from app.api.security import Guard
from app.core.errors import DeviceUnavailable, InvalidRequest
from app.outputs import encoding
from app.service.instrument import Instrument
from app.service.reconstruction import LiveResult

router = APIRouter(prefix="/api/stream", tags=["stream"])

#: the feed re-checks for shutdown this often, s
WAIT_S = 0.5
#: threads encoding JPEGs for all streams together
ENCODE_THREADS = 2
#: a refused stream is told to retry after this long, s
RETRY_AFTER_S = 5
Range = tuple[float, float]
R429: Responses = {429: {
    "description": "too many streams from this client (max_streams_per_client)",
    "content": {"application/json": {"schema": {
        "type": "object", "required": ["detail"], "properties": {"detail": {"type": "string"}}}}}}}


def _jpeg(res: LiveResult, rng: Range) -> bytes:
    return res.cached(("jpeg", rng), lambda: encoding.depth_color_jpeg(res.depth, rng))


class ResultFeed:
    """New live results delivered to the streams of one event loop, and their shared JPEGs.

    One daemon thread waits on the instrument's result slot and hands every new result to
    the loop; it ends when the slot closes (the instrument's shutdown) or the loop does.
    """

    def __init__(self, inst: Instrument, loop: asyncio.AbstractEventLoop) -> None:
        self.inst = inst
        self.loop = loop
        self.seq = 0
        self.latest: LiveResult | None = None
        self._event = asyncio.Event()
        self._encoded: dict[tuple[int, Range], asyncio.Future[bytes]] = {}
        self._pool = ThreadPoolExecutor(ENCODE_THREADS, thread_name_prefix="fringescope-encode")
        self._ended = False
        self._thread = threading.Thread(target=self._run, name="fringescope-stream-feed",
                                        daemon=True)
        self._thread.start()

    @property
    def alive(self) -> bool:
        return not self._ended and not self.loop.is_closed()

    def _run(self) -> None:
        seq, slot = 0, self.inst.results
        try:
            while not slot.closed and not self.loop.is_closed():
                newer, res = slot.wait_newer(seq, WAIT_S)
                if res is None or newer <= seq:
                    continue
                seq = newer
                self.loop.call_soon_threadsafe(self._publish, seq, res)
        except RuntimeError:  # the loop closed between the check and the call
            pass
        finally:
            self._ended = True
            self._pool.shutdown(wait=False)
            with contextlib.suppress(RuntimeError):
                self.loop.call_soon_threadsafe(self._publish, seq, None)  # wake streams to end

    def _publish(self, seq: int, res: LiveResult | None) -> None:
        if res is not None:
            self.seq, self.latest = seq, res
            self._encoded = {k: v for k, v in self._encoded.items() if k[0] == seq}
        event, self._event = self._event, asyncio.Event()
        event.set()

    async def next_after(self, seq: int) -> tuple[int, LiveResult] | None:
        """The newest result after ``seq`` with its sequence number; None once the feed ended."""
        while self.latest is None or self.seq <= seq:
            if self._ended:
                return None
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._event.wait(), WAIT_S)
        return self.seq, self.latest

    async def jpeg(self, seq: int, res: LiveResult, rng: Range) -> bytes:
        """The colormap JPEG of result ``seq`` in ``rng`` (mm), encoded once for all streams."""
        key = (seq, rng)
        future = self._encoded.get(key)
        if future is None:
            future = asyncio.ensure_future(self.loop.run_in_executor(self._pool, _jpeg, res, rng))
            if seq == self.seq:
                self._encoded[key] = future
        return await asyncio.shield(future)  # a stream leaving does not cancel the others' JPEG

    async def frames(self, rng: Range) -> AsyncIterator[bytes]:
        """Each new result once, encoded, until shutdown."""
        seq = 0
        while (item := await self.next_after(seq)) is not None:
            seq, res = item
            yield await self.jpeg(seq, res, rng)


class StreamCap:
    """How many streams each client holds, refusing more than ``limit`` at once."""

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"limit: must be >= 1, got {limit}")
        self.limit = limit
        self._counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def acquire(self, client: str) -> bool:
        with self._lock:
            n = self._counts.get(client, 0)
            if n >= self.limit:
                return False
            self._counts[client] = n + 1
            return True

    def release(self, client: str) -> None:
        with self._lock:
            n = self._counts.get(client, 0) - 1
            if n > 0:
                self._counts[client] = n
            else:
                self._counts.pop(client, None)

    def held(self, client: str) -> int:
        with self._lock:
            return self._counts.get(client, 0)

    def refusal(self) -> str:
        return (f"too many streams from this client: at most {self.limit} at once "
                "(FRINGESCOPE_MAX_STREAMS_PER_CLIENT); close one first")


_SETUP_LOCK = threading.Lock()


def _feed(state: object, inst: Instrument) -> ResultFeed:
    """The app's feed for the running loop (a new one if the loop or the instrument changed)."""
    loop = asyncio.get_running_loop()
    with _SETUP_LOCK:
        feed: ResultFeed | None = getattr(state, "stream_feed", None)
        if feed is None or feed.loop is not loop or feed.inst is not inst or not feed.alive:
            feed = ResultFeed(inst, loop)
            setattr(state, "stream_feed", feed)  # noqa: B010 (app.state is dynamic)
        return feed


def _cap(state: object, limit: int) -> StreamCap:
    with _SETUP_LOCK:
        cap: StreamCap | None = getattr(state, "stream_cap", None)
        if cap is None:
            cap = StreamCap(limit)
            setattr(state, "stream_cap", cap)  # noqa: B010
        return cap


def _client(scope: Scope, guard: object) -> str:
    if isinstance(guard, Guard):
        return guard.client_address(scope)
    return str((scope.get("client") or ("unknown", 0))[0])


async def stream_instrument(request: Request) -> Instrument:
    """The instrument, without the worker-thread hop a plain dependency costs."""
    inst = getattr(request.app.state, "instrument", None)
    if not isinstance(inst, Instrument):
        raise DeviceUnavailable("instrument not started")
    return inst


class _CappedStream(StreamingResponse):
    """A streaming response that gives its client's stream slot back however it ends."""

    def __init__(self, content: AsyncIterator[bytes], cap: StreamCap, client: str, **kwargs: object
                 ) -> None:
        super().__init__(content, **kwargs)  # type: ignore[arg-type]
        self._cap, self._client = cap, client

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._cap.release(self._client)


@router.websocket("/depth")
async def depth_ws(
    websocket: WebSocket,
    min_mm: float | None = Query(None),
    max_mm: float | None = Query(None),
) -> None:
    """Sends every new depth colormap as one binary JPEG message, at the depth rate.

    Over the per-client cap the handshake is refused with HTTP 429 (close code 1013 where the
    server cannot send an HTTP answer)."""
    state = websocket.app.state
    inst = getattr(state, "instrument", None)
    try:
        rng = encoding.check_range_mm(min_mm, max_mm)
    except InvalidRequest as exc:
        await websocket.close(code=1008, reason=exc.detail[:120])
        return
    cap = _cap(state, state.settings.max_streams_per_client)
    client = _client(websocket.scope, getattr(state, "guard", None))
    if not cap.acquire(client):
        if "websocket.http.response" in websocket.scope.get("extensions", {}):
            await websocket.send_denial_response(JSONResponse(
                {"detail": cap.refusal()}, status_code=429,
                headers={"Retry-After": str(RETRY_AFTER_S)}))
        else:
            await websocket.close(code=1013, reason=cap.refusal()[:120])
        return
    try:
        await websocket.accept()
        if not isinstance(inst, Instrument):
            await websocket.close(code=1011, reason="instrument not started")
            return
        await _pump(websocket, _feed(state, inst), rng)
    finally:
        cap.release(client)


async def _pump(websocket: WebSocket, feed: ResultFeed, rng: Range) -> None:
    async def pump() -> None:
        async for data in feed.frames(rng):
            await websocket.send_bytes(data)

    async def until_disconnect() -> None:
        # notice a client leaving (or the server shutting down) even while no result arrives:
        # otherwise the handler waits forever and blocks uvicorn's graceful shutdown
        while (await websocket.receive())["type"] != "websocket.disconnect":
            pass

    tasks = {asyncio.ensure_future(pump()), asyncio.ensure_future(until_disconnect())}
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            if not task.cancelled() and isinstance(task.exception(),
                                                   (WebSocketDisconnect, RuntimeError)):
                return  # the client went away
            task.result()
    finally:
        for task in tasks:
            task.cancel()


@router.get("/depth.mjpeg",
            responses={200: {"content": {"multipart/x-mixed-replace": {}}}, **R429, **R422,
                       **COMMON})
async def depth_mjpeg(
    request: Request,
    inst: Annotated[Instrument, Depends(stream_instrument)],
    min_mm: float | None = Query(None, allow_inf_nan=False),
    max_mm: float | None = Query(None, allow_inf_nan=False),
    frames: int | None = Query(None, ge=1,
                               description="end after this many images (default: never)"),
) -> StreamingResponse:
    """The same images as a ``multipart/x-mixed-replace`` MJPEG stream (an <img> can show it)."""
    rng = encoding.check_range_mm(min_mm, max_mm)
    state = request.app.state
    cap = _cap(state, state.settings.max_streams_per_client)
    client = _client(request.scope, getattr(state, "guard", None))
    if not cap.acquire(client):
        raise HTTPException(status_code=429, detail=cap.refusal(),
                            headers={"Retry-After": str(RETRY_AFTER_S)})
    feed = _feed(state, inst)

    async def body() -> AsyncIterator[bytes]:
        sent = 0
        async for data in feed.frames(rng):
            yield (b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                   + str(len(data)).encode() + b"\r\n\r\n" + data + b"\r\n")
            sent += 1
            if frames is not None and sent >= frames:
                break
        yield b"--frame--\r\n"

    return _CappedStream(body(), cap, client,
                         media_type="multipart/x-mixed-replace; boundary=frame",
                         headers={"Cache-Control": "no-store"})


__all__ = ["ResultFeed", "StreamCap", "router"]
