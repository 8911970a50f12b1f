"""The dashboard behind a token (issue 16): it asks once, then everything works.

A real uvicorn server with ``FRINGESCOPE_API_TOKEN`` set (every data route needs it),
headless Chromium: the page prompts for the token exactly once, the live depth image,
status, WebSocket stream and the 3-D viewer iframe then load without a single 401, and
a reload within the browser session does not ask again.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.helpers.dashboard import CHROMIUM, CHROMIUM_ARGS, EXPOSURE_MS, live_server

pytestmark = [pytest.mark.browser, pytest.mark.slow]

TOKEN = "browser-token_7"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> Iterator[str]:
    with live_server(tmp_path_factory, request, "auth-data", token=TOKEN) as base:
        assert httpx.get(f"{base}/api/status").status_code == 401
        yield base


def test_dashboard_asks_once_then_works(server: str) -> None:
    from playwright.sync_api import sync_playwright

    dialogs: list[str] = []
    refused: list[str] = []
    errors: list[str] = []

    def on_dialog(dialog: Any) -> None:
        dialogs.append(dialog.message)
        dialog.accept(TOKEN)

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            # Playwright's wait_for_function evaluates its string with eval, which the dashboard's
            # CSP forbids; tests/browser/test_csp.py checks the page under the CSP
            pg = browser.new_page(viewport={"width": 1400, "height": 900},
                                  bypass_csp=True)
            pg.on("dialog", on_dialog)
            pg.on("response", lambda r: refused.append(r.url) if r.status in (401, 403) else None)
            pg.on("pageerror", lambda exc: errors.append(str(exc)))
            pg.goto(server + "/", wait_until="load")
            pg.wait_for_function(
                "window.fringescope && window.fringescope.framesShown >= 2", timeout=90_000
            )
            pg.wait_for_function(
                "document.querySelector('#state').textContent === 'running'", timeout=30_000
            )
            assert len(dialogs) == 1 and "token" in dialogs[0].lower()
            # the 3-D viewer iframe (no header possible) loads on the session cookie
            frame = pg.frame_locator("#viewer3d")
            frame.locator("body").wait_for(timeout=30_000)
            cookies = {c["name"]: c for c in pg.context.cookies()}
            assert (
                cookies["fringescope_token"]["httpOnly"]
                and cookies["fringescope_token"]["sameSite"] == "Strict"
            )
            assert cookies["fringescope_token"]["expires"] == -1  # a browser-session cookie

            pg.reload(wait_until="load")
            pg.wait_for_function(
                "window.fringescope && window.fringescope.framesShown >= 1", timeout=90_000
            )
            assert len(dialogs) == 1  # not asked again in this browser session
            # a change (bearer header from the kept token) works too
            status = pg.evaluate(
                "fetch('/api/exposure', {method: 'PUT',"
                " headers: {'Content-Type': 'application/json',"
                " Authorization: 'Bearer ' + sessionStorage.getItem('fringescope_token')},"
                f" body: JSON.stringify({{exposure_ms: {EXPOSURE_MS}}})}}).then(r => r.status)"
            )
            assert status == 200
            assert not refused, refused
            assert not errors, errors
        finally:
            browser.close()
