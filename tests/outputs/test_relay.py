"""The /viser relay through a real uvicorn: page, WebSocket both ways, subprotocol, disconnects."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import httpx
import msgspec.msgpack
import pytest
import viser
import websockets
from fastapi import FastAPI
from viser import _messages

from app.outputs.relay import viewer_router
from app.outputs.viewer import Viewer, cloud_arrays
from tests.helpers.outputs import SurfaceSource, port_is_free, serve, surface_result, wait_for

SUBPROTOCOL = f"viser-v{viser.__version__}"


@pytest.fixture()
def rig() -> Iterator[tuple[SurfaceSource, Viewer, FastAPI, str]]:
    source = SurfaceSource()
    viewer = Viewer(source, max_points=3000, max_rate_hz=30.0)
    app = FastAPI()
    app.include_router(viewer_router(viewer))

    @app.get("/_relay_tasks")
    async def relay_tasks() -> list[str]:  # test-only: relay tasks alive in the server loop
        return sorted(
            t.get_name() for t in asyncio.all_tasks() if t.get_name().startswith("viser-relay")
        )

    viewer.start()
    try:
        with serve(app) as host:
            yield source, viewer, app, host
    finally:
        viewer.stop()


def _clients(viewer: Viewer) -> int:
    return len(viewer.server._websock_server._client_state_from_id)


def test_relay_serves_the_client_page(rig: tuple[SurfaceSource, Viewer, FastAPI, str]) -> None:
    _, viewer, _, host = rig
    direct = httpx.get(f"http://127.0.0.1:{viewer.port}/").content
    page = httpx.get(f"http://{host}/viser/")
    assert page.status_code == 200
    assert page.headers["content-type"].startswith("text/html")
    assert page.content == direct and b'<div id="root">' in page.content
    # gzip passes through untouched (httpx decodes it here).
    assert page.headers.get("content-encoding") == "gzip"
    redirect = httpx.get(f"http://{host}/viser", follow_redirects=False)
    assert redirect.status_code == 307 and redirect.headers["location"] == "/viser/"
    assert httpx.get(f"http://{host}/viser/no-such-file.js").status_code == 404


def _camera_message() -> bytes:
    """What the viser client sends first (it counts as connected from then on)."""
    camera = _messages.ViewerCameraMessage(
        wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0), fov=1.0, near=0.01, far=1000.0,
        image_height=480, image_width=640, look_at=(0.0, 0.0, 60.0), up_direction=(0.0, -1.0, 0.0))
    return bytes(msgspec.msgpack.encode(camera.as_serializable_dict()))


def test_relay_websocket_both_ways(rig: tuple[SurfaceSource, Viewer, FastAPI, str]) -> None:
    source, viewer, _, host = rig
    result = surface_result(120, 160)
    n_points = len(cloud_arrays(result, viewer.max_points)[0])
    source.publish(result)
    # Nobody watching: the viewer keeps the result but does no encoding work.
    assert not wait_for(lambda: viewer.updates > 0, 1.0)
    assert viewer.last_seq == 1
    uuid = viewer._gui["exposure"]._impl.uuid

    async def session() -> int:
        received = 0
        # The browser opens ws://host/viser (page URL without the trailing slash).
        async with websockets.connect(f"ws://{host}/viser", subprotocols=[SUBPROTOCOL],
                                      max_size=None) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            await ws.send(_camera_message())
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and received < n_points * 15:
                try:
                    received += len(await asyncio.wait_for(ws.recv(), 1.0))
                except TimeoutError:
                    continue
            # Browser → server: what the viser client sends when the slider is dragged.
            update = _messages.GuiUpdateMessage(uuid, {"value": 42.0})
            await ws.send(msgspec.msgpack.encode(update.as_serializable_dict()))
            ok = await asyncio.to_thread(
                wait_for, lambda: ("set_exposure", 42.0) in source.calls, 5.0
            )
            assert ok, source.calls
        return received

    received = asyncio.run(session())
    assert viewer.updates == 1 and viewer.last_point_count == n_points
    # Point cloud (12 B/point) and colours (3 B/point) came through the relay.
    assert received >= n_points * 15
    assert wait_for(lambda: _clients(viewer) == 0, 5)


def test_relay_passes_the_version_check_through(
    rig: tuple[SurfaceSource, Viewer, FastAPI, str],
) -> None:
    _, viewer, _, host = rig

    async def session() -> tuple[int | None, str]:
        async with websockets.connect(f"ws://{host}/viser/", subprotocols=["viser-v0.0.0"]) as ws:
            with pytest.raises(websockets.ConnectionClosed):
                await asyncio.wait_for(ws.recv(), 5)
            assert ws.close_code is not None
            return ws.close_code, ws.close_reason or ""

    code, reason = asyncio.run(session())
    assert code == 1002 and "Version mismatch" in reason


def test_relay_cleans_up_after_abrupt_disconnects(
    rig: tuple[SurfaceSource, Viewer, FastAPI, str],
) -> None:
    source, viewer, _, host = rig
    source.publish(surface_result(60, 80))

    async def drop_connections() -> None:
        for _ in range(3):
            ws = await websockets.connect(f"ws://{host}/viser", subprotocols=[SUBPROTOCOL])
            await asyncio.wait_for(ws.recv(), 5)
            assert _clients(viewer) >= 1
            ws.transport.abort()  # no close handshake: a browser tab killed
        await asyncio.sleep(0.1)

    asyncio.run(drop_connections())
    assert wait_for(lambda: _clients(viewer) == 0, 10), _clients(viewer)
    assert wait_for(lambda: httpx.get(f"http://{host}/_relay_tasks").json() == [], 10)


def test_relay_closes_the_browser_side_when_the_viewer_stops(
    rig: tuple[SurfaceSource, Viewer, FastAPI, str],
) -> None:
    _, viewer, _, host = rig
    port = viewer.port

    async def session() -> None:
        async with websockets.connect(f"ws://{host}/viser", subprotocols=[SUBPROTOCOL]) as ws:
            await asyncio.wait_for(ws.recv(), 5)
            await asyncio.to_thread(viewer.stop)
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    await asyncio.wait_for(ws.recv(), 5)

    asyncio.run(session())
    assert port_is_free(port)
    assert wait_for(lambda: httpx.get(f"http://{host}/_relay_tasks").json() == [], 10)
    # With the viewer stopped the relay answers clearly instead of hanging.
    assert httpx.get(f"http://{host}/viser/").status_code == 503

    async def refused() -> int | None:
        async with websockets.connect(f"ws://{host}/viser", subprotocols=[SUBPROTOCOL]) as ws:
            with pytest.raises(websockets.ConnectionClosed):
                await asyncio.wait_for(ws.recv(), 5)
            return ws.close_code

    assert asyncio.run(refused()) == 1013


def test_router_rejects_bad_prefix() -> None:
    with pytest.raises(ValueError, match="^prefix"):
        viewer_router(object(), prefix="viser/")
