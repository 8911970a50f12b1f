"""The live 3-D view: a viser server on loopback fed from the Instrument's latest result.

viser runs its own thread and port; :mod:`app.outputs.relay` relays it under ``/viser/``
so the browser needs one port. One update thread waits for new results and pushes the
decimated point cloud (float32, coloured by height with the dashboard's TURBO table or
by texture), the depth colormap and the texture, each update grouped in
``server.atomic()`` and handles updated in place. It is paced: at most ``max_rate_hz``
updates a second (rolling mode makes depth maps faster than any browser draws them),
always showing the newest result.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import viser

from app.core.limits import DEFAULT_LED, EXPOSURE_RANGE_MS, LEDS
from app.core.records import Status
from app.outputs.cloud import (
    COLOR_MODES,
    PANEL_WIDTH_PX,
    cloud_arrays,
    decimation_step,
    initial_view,
    point_size_mm,
    preview,
)
from app.outputs.encoding import DEFAULT_RANGE_MM
from app.outputs.encoding import texture_u8 as _texture_u8
from app.recon.colormap import depth_colormap
from app.service.priority import lower_this_threads_priority
from app.service.reconstruction import LiveResult
from app.service.store import LatestSlot

log = logging.getLogger(__name__)

__all__ = ["Viewer", "cloud_arrays", "decimation_step", "initial_view"]


class ViewedInstrument(Protocol):
    """What the viewer uses of the instrument: the latest-result slot, the status, two controls."""

    @property
    def store(self) -> LatestSlot[LiveResult]: ...
    def status(self) -> Status | Mapping[str, Any]: ...
    def set_exposure(self, exposure_ms: float) -> float: ...
    def set_led(self, led: str) -> str: ...


class Viewer:
    """viser 3-D view of the Instrument's latest result, with exposure/LED controls.

    Parameters
    ----------
    instrument
        Has ``store`` (an :class:`app.service.store.LatestSlot` of results), ``status()``
        (a :class:`~app.core.records.Status` or its dict), ``set_exposure(exposure_ms)``
        and ``set_led(led)``.
    host : str
        Bind address; loopback by default (the browser reaches it through the relay).
    port : int
        0 picks a free port; read :attr:`port` after :meth:`start`.
    max_points : int
        Upper bound on the points sent per update.
    max_rate_hz : float
        Upper bound on updates per second.
    range_mm : (float, float)
        Initial height colour range (the dashboard's default, 0–35 mm).
    only_when_watched : bool
        Skip the encoding work while no browser is connected; the newest result is sent
        as soon as one connects (viser replays the scene to later clients anyway).
    measure_source : callable, optional
        Returns the dashboard's measurements (kind + pixels) to draw on the cloud.
    """

    def __init__(
        self,
        instrument: ViewedInstrument,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        max_points: int = 300_000,
        max_rate_hz: float = 15.0,
        range_mm: tuple[float, float] = DEFAULT_RANGE_MM,
        only_when_watched: bool = True,
        measure_source: Callable[[], list[dict[str, Any]]] | None = None,
        change_source: Callable[[], npt.NDArray[np.float32] | None] | None = None,
    ) -> None:
        if max_points < 1:
            raise ValueError(f"max_points: must be >= 1, got {max_points}")
        if not max_rate_hz > 0:
            raise ValueError(f"max_rate_hz: must be > 0, got {max_rate_hz}")
        self._instrument = instrument
        self._store = instrument.store
        self._host = host
        self._requested_port = port
        self.max_points = max_points
        self._min_interval_s = 1.0 / max_rate_hz
        self._range_mm = (float(range_mm[0]), float(range_mm[1]))
        self._color_mode = "height"
        self.only_when_watched = only_when_watched
        self._server: viser.ViserServer | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._redraw = threading.Event()
        self._lock = threading.Lock()
        self._cloud: Any = None
        self._depth_image: Any = None
        self._texture_image: Any = None
        self._camera_placed = False
        self._gui: dict[str, Any] = {}
        # the dashboard's measurements (kind + pixels) drawn on the cloud
        self.measure_source = measure_source
        # the newest change map's Δ (mm) for the "change" colours (None: none)
        self.change_source = change_source
        self._measure_nodes: list[Any] = []
        self.updates = 0  # results pushed to viser
        self.last_seq = 0
        self.last_point_count = 0

    # -- lifecycle -----------------------------------------------------------------
    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("Viewer.port: not started")
        return int(self._server.get_port())

    @property
    def server(self) -> viser.ViserServer:
        if self._server is None:
            raise RuntimeError("Viewer.server: not started")
        return self._server

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        if self._server is not None:
            raise RuntimeError("Viewer.start: already started")
        server = viser.ViserServer(host=self._host, port=self._requested_port, verbose=False)
        self._server = server
        try:
            server.gui.configure_theme(
                dark_mode=True, show_logo=False, show_share_button=False, control_width="small"
            )
            # Camera frame: x right, y down, z along the optical axis.
            server.scene.set_up_direction("-y")
            self._build_gui(server)
        except Exception:
            server.stop()
            self._server = None
            raise
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="viewer-update", daemon=True)
        self._thread.start()
        log.info("viser 3-D view on %s:%d", self._host, self.port)

    def stop(self) -> None:
        """Stop the update thread and the viser server (its port is free afterwards)."""
        self._stop.set()
        self._redraw.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            if self._thread.is_alive():
                log.error("viewer update thread did not stop within 10 s")
            self._thread = None
        if self._server is not None:
            self._server.stop()
            self._server = None
        self._cloud = self._depth_image = self._texture_image = None
        self._camera_placed = False
        self._gui.clear()

    def __enter__(self) -> Viewer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- GUI -------------------------------------------------------------------------
    def _build_gui(self, server: viser.ViserServer) -> None:
        gui = server.gui
        status = self._safe_status()
        with gui.add_folder("Acquisition"):
            exposure = gui.add_slider(
                "Exposure (ms)", min=EXPOSURE_RANGE_MS[0], max=EXPOSURE_RANGE_MS[1], step=1.0,
                initial_value=float(np.clip(status.get("exposure_ms", 30.0), *EXPOSURE_RANGE_MS)),
            )
            led0 = status.get("led", DEFAULT_LED)
            led = gui.add_dropdown("LED", LEDS, initial_value=led0 if led0 in LEDS else DEFAULT_LED)
            info = gui.add_markdown("waiting for depth…")
        with gui.add_folder("Display"):
            color = gui.add_dropdown("Colour by", COLOR_MODES, initial_value=self._color_mode)
            lo = gui.add_number("Height min (mm)", self._range_mm[0], step=0.5)
            hi = gui.add_number("Height max (mm)", self._range_mm[1], step=0.5)
        # Collapsed: the dashboard shows both images large; here they are on demand.
        with gui.add_folder("Images", expand_by_default=False):
            blank = np.zeros((8, 8, 3), dtype=np.uint8)
            self._depth_image = gui.add_image(blank, label="Depth (colormap)", format="jpeg")
            self._texture_image = gui.add_image(blank, label="Texture", format="jpeg")
        self._gui = {"exposure": exposure, "led": led, "info": info, "color": color,
                     "min": lo, "max": hi}

        # A value assigned here (client None) mirrors the instrument: don't echo it back.
        @exposure.on_update
        def _(event: Any) -> None:
            if event.client is not None:
                self._call("set_exposure", float(event.target.value))

        @led.on_update
        def _(event: Any) -> None:
            if event.client is not None:
                self._call("set_led", str(event.target.value))

        @color.on_update
        def _(event: Any) -> None:
            self._color_mode = str(event.target.value)
            self._redraw.set()

        def set_range(_: Any) -> None:
            lo_mm, hi_mm = float(lo.value), float(hi.value)
            if hi_mm > lo_mm:
                self._range_mm = (lo_mm, hi_mm)
                self._redraw.set()

        lo.on_update(set_range)
        hi.on_update(set_range)

    def _call(self, method: str, value: Any) -> None:
        try:
            getattr(self._instrument, method)(value)
        except Exception as exc:  # a rejected value must not kill viser's callback thread
            log.warning("viewer: %s(%r) failed: %s", method, value, exc)
            if self._server is not None:
                self._server.add_notification(
                    "Rejected", f"{method}({value!r}): {exc}", color="red", auto_close_seconds=5.0
                )

    def _safe_status(self) -> dict[str, Any]:
        try:
            status = self._instrument.status()
            return status.to_dict() if isinstance(status, Status) else dict(status)
        except Exception as exc:
            log.debug("viewer: status() failed: %s", exc)
            return {}

    def _mirror_status(self) -> None:
        status = self._safe_status()
        gui = self._gui
        if not status or not gui:
            return
        exposure_ms = status.get("exposure_ms")
        if isinstance(exposure_ms, int | float) and math.isfinite(exposure_ms):
            gui["exposure"].value = float(np.clip(round(exposure_ms), *EXPOSURE_RANGE_MS))
        if status.get("led") in LEDS:
            gui["led"].value = status["led"]

        def fmt(key: str, spec: str) -> str:
            value = status.get(key)
            return format(value, spec) if isinstance(value, int | float) else "–"

        gui["info"].content = (
            f"**{status.get('state', '?')}** · depth {fmt('depth_fps', '.2f')}/s · "
            f"camera {fmt('camera_fps', '.1f')}/s · latency {fmt('latency_ms', '.0f')} ms · "
            f"{self.last_point_count:,} points"
        )

    # -- updates ---------------------------------------------------------------------
    def _run(self) -> None:
        lower_this_threads_priority()  # bulk work: the event loop answers first
        last_push = -math.inf
        last_status = -math.inf
        shown: LiveResult | None = None
        dirty = False  # `shown` differs from what the browsers have
        while not self._stop.is_set():
            seq, result = self._store.wait_newer(self.last_seq, 0.25)
            if result is None and self._store.closed:
                self._stop.wait(0.25)  # the instrument shut down first: don't spin
            now = time.monotonic()
            if now - last_status >= 0.5:
                last_status = now
                self._mirror_status()
            if result is not None:
                # Pacing: wait out the interval, then take the newest result there is.
                wait_s = last_push + self._min_interval_s - now
                if wait_s > 0 and self._stop.wait(wait_s):
                    break
                seq2, newest = self._store.latest()
                if newest is not None and seq2 >= seq:
                    seq, result = seq2, newest
                self.last_seq = seq
                shown, dirty = result, True
            if self._redraw.is_set():
                self._redraw.clear()
                dirty = shown is not None
            # Nobody watching: keep the newest and send it when a browser connects.
            if not dirty or shown is None or (self.only_when_watched and not self._watched()):
                continue
            try:
                self._show(shown)
            except Exception:
                log.exception("viewer: update failed")
            dirty = False
            last_push = time.monotonic()

    def _watched(self) -> bool:
        server = self._server
        return server is not None and len(server.get_clients()) > 0

    def _show(self, result: LiveResult) -> None:
        server = self._server
        if server is None:
            return
        change = (self.change_source() if self.change_source is not None
                  and self._color_mode == "change" else None)
        xyz, colors, step = cloud_arrays(result, self.max_points, self._color_mode, self._range_mm,
                                         change)
        # Previews from a strided copy: colouring all 1.4 Mpx for a 360 px panel is waste.
        k = max(1, np.asarray(result.depth).shape[1] // (2 * PANEL_WIDTH_PX))
        depth_rgb = preview(depth_colormap(np.asarray(result.depth)[::k, ::k], self._range_mm))
        gray = _texture_u8(np.asarray(result.texture)[::k, ::k], float(result.full_scale))
        texture = preview(np.repeat(gray[..., None], 3, axis=2))
        size_mm = point_size_mm(xyz, step, np.asarray(result.points))
        with self._lock, server.atomic():
            if self._cloud is None:
                self._cloud = server.scene.add_point_cloud(
                    "/depth/points", xyz, colors, point_size=size_mm,
                    precision="float32", point_shading="flat",
                )
            else:
                self._cloud.points = xyz
                self._cloud.colors = colors
                self._cloud.point_size = size_mm
            self._cloud.visible = len(xyz) > 0
            if self._depth_image is not None:
                self._depth_image.image = depth_rgb
                self._texture_image.image = texture
            if not self._camera_placed and len(xyz) > 0:
                self._place_camera(server, xyz)
            self._show_measurements(server, result)
        self.updates += 1
        self.last_point_count = len(xyz)

    def _show_measurements(self, server: viser.ViserServer, result: LiveResult) -> None:
        """The measure tool's lines and values (issue 17), re-measured on this result."""
        for node in self._measure_nodes:
            node.remove()
        self._measure_nodes = []
        specs = self.measure_source() if self.measure_source is not None else []
        if not specs:
            return
        from app.service.measure import calibration_terms, measurement_segments

        terms = calibration_terms(getattr(self._instrument, "calibration", None))
        segs, labels = measurement_segments(result, specs, *terms)
        if len(segs):
            self._measure_nodes.append(server.scene.add_line_segments(
                "/measure/lines", segs, (255, 255, 255), thickness=3.0, thickness_units="screen"))
        for i, (pos, text) in enumerate(labels):
            self._measure_nodes.append(server.scene.add_label(f"/measure/label_{i}", text,
                                                              position=pos))

    def _place_camera(self, server: viser.ViserServer, xyz: npt.NDArray[np.float32]) -> None:
        """Start every browser near the scope's own viewpoint, tilted to show the relief."""
        position, look_at, fov_rad = initial_view(xyz)
        up = np.array([0.0, -1.0, 0.0])
        server.initial_camera.position = position
        server.initial_camera.look_at = look_at
        server.initial_camera.up = up
        server.initial_camera.fov = fov_rad
        for client in server.get_clients().values():
            client.camera.position = position
            client.camera.look_at = look_at
            client.camera.up_direction = up
            client.camera.fov = fov_rad
        self._camera_placed = True
