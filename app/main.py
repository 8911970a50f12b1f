"""The FastAPI application: ``create_app(settings)`` and its lifespan.

Sections: (1) the Instrument, (2) the REST/stream routes, (3) the 3-D viewer relay under
``/viser/`` (when enabled and installed), (4) the dashboard from ``static/`` at ``/``.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from fastapi import FastAPI
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

import app as app_package
from app import __version__
from app.api import api_router
from app.api.auth import router as auth_router
from app.api.bodylimit import install_body_limits
from app.api.errors import install_api_fallback, install_error_handlers
from app.api.security import install_security
from app.config import Settings
from app.service.instrument import Instrument
from app.service.poses import TrackerPoses

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt
    from fastapi import APIRouter

    from app.outputs.igtl import IgtlServer
    from app.outputs.viewer import Viewer

log = logging.getLogger("fringescope.main")

STATIC_DIR = Path(app_package.__file__).resolve().parent.parent / "static"


def _make_viewer(settings: Settings,
                 instrument: Instrument) -> tuple[Viewer, APIRouter] | tuple[None, None]:
    """(viewer, router) or (None, None) when disabled or the viewer package is absent."""
    if not settings.viewer:
        return None, None
    try:
        from app.outputs.relay import viewer_router
        from app.outputs.viewer import Viewer
    except ImportError as exc:
        log.warning("3-D viewer unavailable: %s", exc)
        return None, None
    recorder = instrument.recorder
    viewer = Viewer(instrument, port=settings.viewer_port, max_points=settings.viewer_max_points,
                    measure_source=lambda: recorder.measurements,
                    change_source=instrument.change.latest_delta)
    return viewer, viewer_router(viewer)


def _make_igtl(settings: Settings, instrument: Instrument,
               poses: TrackerPoses) -> IgtlServer | None:
    """The OpenIGTLink server, or None when ``igtl_port`` is unset."""
    if settings.igtl_port is None:
        return None
    from app.outputs.igtl import IgtlServer, check_igtl_settings, image_placement

    check_igtl_settings(settings.igtl_host, settings.igtl_port, settings.igtl_allow_remote)

    def placement() -> npt.NDArray[np.float64] | None:
        cal = instrument.calibration
        if cal is None:
            return None
        try:
            return image_placement(cal.camera_matrix, cal.plane_normal, cal.plane_offset_mm)
        except ValueError:
            return None

    return IgtlServer(instrument.results, host=settings.igtl_host, port=settings.igtl_port,
                      max_points=settings.igtl_max_points,
                      status=lambda: instrument.status().to_dict(), placement=placement,
                      poses=poses, changes=instrument.change.slot)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The Fringescope web application (the Instrument starts and stops with its lifespan)."""
    settings = settings or Settings()
    # (1) the Instrument — built now (cheap), started in the lifespan. Every part gets its
    # collaborators in its constructor: the OpenIGTLink server writes the tracker's poses,
    # the Instrument's recorder reads them (and the server sends the Instrument's status).
    poses = TrackerPoses()
    instrument = Instrument(settings, poses=None if settings.igtl_port is None else poses)
    recorder = instrument.recorder
    igtl = _make_igtl(settings, instrument, poses)
    # the dashboard's measurements in the 3-D view too
    viewer, viewer_routes = _make_viewer(settings, instrument)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        instrument.start()
        if igtl is not None:
            try:
                igtl.start()  # a taken port fails the startup, like the HTTP port
            except OSError:
                instrument.close()
                raise
        if viewer is not None:
            try:
                viewer.start()
            except Exception as exc:  # the 3-D view is optional; the instrument is not
                log.warning("3-D viewer failed to start: %s", exc)
                instrument.calibrations.warnings.append(f"3-D viewer failed to start: {exc}")
        try:
            yield
        finally:
            recorder.close()  # finish a running recording before the devices stop
            if viewer is not None:
                viewer.stop()
            if igtl is not None:
                igtl.stop()
            instrument.close()

    app = FastAPI(title="Fringescope", version=__version__, lifespan=lifespan,
                  description="Structured-illumination 3-D laparoscope: live metric depth.")
    app.state.settings = settings
    app.state.instrument = instrument
    app.state.viewer = viewer
    app.state.igtl = igtl
    install_error_handlers(app)
    install_security(app, settings)  # token, CORS, WebSocket Origin, upload limit
    install_body_limits(app)  # per-route body size, JSON depth, finite numbers (innermost)
    app.state.recorder = recorder

    # (2) REST and streams
    app.include_router(api_router())
    app.include_router(auth_router)  # /healthz, /api/auth, /api/login, /api/logout

    # (3) the 3-D viewer relay
    if viewer_routes is not None:
        app.include_router(viewer_routes)
    install_api_fallback(app)  # after every API route: unknown /api paths 404, wrong methods 405

    # (4) the dashboard
    if (STATIC_DIR / "index.html").is_file():
        app.mount("/", StaticFiles(directory=STATIC_DIR, html=True), name="static")
    else:
        @app.get("/", include_in_schema=False)
        def no_dashboard() -> JSONResponse:
            return JSONResponse({"detail": "dashboard not installed; the API is at /docs"},
                                status_code=404)

    return app
