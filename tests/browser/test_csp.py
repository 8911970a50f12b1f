"""The dashboard under its Content-Security-Policy, behind a token, in headless Chromium.

The other browser tests bypass the CSP (Playwright's ``wait_for_function`` needs eval);
this one keeps it: the page must show live depth, the status and the 3-D viewer iframe
without a single CSP violation, and the security headers must reach the browser.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest

from app.api.security import DASHBOARD_CSP
from tests.helpers.dashboard import CHROMIUM, CHROMIUM_ARGS, live_server

pytestmark = [pytest.mark.browser, pytest.mark.slow]

TOKEN = "csp-browser-token_9"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> Iterator[str]:
    with live_server(tmp_path_factory, request, "csp-data", token=TOKEN) as base:
        yield base


def _poll(pg: Any, expression: str, timeout_s: float) -> Any:
    """``page.evaluate(expression)`` until truthy (evaluate is not subject to the page's CSP)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = pg.evaluate(expression)
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {expression}")


def test_dashboard_works_under_its_csp(server: str) -> None:
    from playwright.sync_api import sync_playwright

    violations: list[str] = []
    errors: list[str] = []
    headers: dict[str, str] = {}

    def on_console(msg: Any) -> None:
        if "Content Security Policy" in msg.text or "Content-Security-Policy" in msg.text:
            violations.append(msg.text)
        elif msg.type == "error":
            errors.append(msg.text)

    def on_response(r: Any) -> None:
        if r.url.rstrip("/") == server:
            headers.update(r.headers)

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            pg = browser.new_page(viewport={"width": 1400, "height": 900})
            pg.on("dialog", lambda d: d.accept(TOKEN))
            pg.on("console", on_console)
            pg.on("pageerror", lambda exc: errors.append(str(exc)))
            pg.on("response", on_response)
            pg.goto(server + "/", wait_until="load")
            _poll(pg, "window.fringescope && window.fringescope.framesShown >= 2", 90)
            _poll(pg, "document.querySelector('#state').textContent === 'running'", 30)
            assert headers["content-security-policy"] == DASHBOARD_CSP
            assert headers["x-frame-options"] == "SAMEORIGIN"
            assert headers["x-content-type-options"] == "nosniff"
            assert headers["referrer-policy"] == "no-referrer"
            # the 3-D viewer in its same-origin iframe (SAMEORIGIN, frame-src 'self') renders
            frame = pg.frame_locator("#viewer3d")
            frame.locator("canvas").first.wait_for(timeout=60_000)
            assert not violations, violations
            assert not errors, errors
        finally:
            browser.close()
