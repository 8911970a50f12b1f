"""The dashboard's browser-test fixtures: one real server on the simulator, one Chromium page.

``server`` needs the ``browser_calibration_file`` fixture (tests/browser/conftest.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.config import Settings
from tests.helpers.outputs import serve, wait_for

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
# Console messages that are not errors of ours: none so far (keep this list short).
IGNORED_CONSOLE: tuple[str, ...] = ()
EXPOSURE_MS = 60.0


@contextmanager
def live_server(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest, name: str,
                *, token: str | None = None, **overrides: Any) -> Iterator[str]:
    """A served app on the simulator once live depth flows (2 results), at its base URL.

    Skips without Chromium. ``overrides`` are Settings fields; a long exposure by default leaves
    the real-time simulator slack on a busy 2-core machine.
    """
    if not CHROMIUM.exists():
        pytest.skip("Chromium not installed at /usr/bin/chromium (make test installs it)")
    from app.main import create_app

    calibration = request.getfixturevalue("browser_calibration_file")
    fields: dict[str, Any] = {"sim_seed": 7, "exposure_ms": EXPOSURE_MS,
                              "viewer_max_points": 100_000}
    settings = Settings(data_dir=tmp_path_factory.mktemp(name), calibration_file=calibration,
                        api_token=token, **(fields | overrides))
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    with serve(create_app(settings)) as host:
        base = f"http://{host}"
        def published() -> bool:
            return httpx.get(f"{base}/api/status", headers=auth).json()["results_published"] >= 2

        ok = wait_for(published, 600, 0.5)
        assert ok, httpx.get(f"{base}/api/status", headers=auth).json()
        yield base


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory,
           request: pytest.FixtureRequest) -> Iterator[str]:
    with live_server(tmp_path_factory, request, "fringescope-data") as base:
        yield base


@pytest.fixture(scope="module")
def page(server: str) -> Iterator[tuple[Any, list[str]]]:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            # Playwright's wait_for_function evaluates its string with eval, which the dashboard's
            # CSP forbids; tests/browser/test_csp.py checks the page under the CSP
            pg = browser.new_page(viewport={"width": 1600, "height": 1000},
                                  bypass_csp=True)

            def on_console(msg: Any) -> None:
                if msg.type == "error" and not any(s in msg.text for s in IGNORED_CONSOLE):
                    errors.append(f"console: {msg.text} @ {msg.location}")

            pg.on("console", on_console)
            pg.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
            pg.goto(server + "/", wait_until="load")
            pg.wait_for_function("window.fringescope && window.fringescope.framesShown >= 1",
                                 timeout=60_000)
            yield pg, errors
        finally:
            browser.close()
