"""A first start shows what it is doing: the dashboard names the start-up phase and its progress.

A real server on an empty data folder (no calibration: the simulator calibrates itself, as a
first ``make run`` does) and a real Chromium page: while ``/api/status`` says ``calibrating``
with its ``phase`` and ``progress``, the page shows that phase with its percentage, once.
"""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest

from app.config import Settings
from tests.helpers.dashboard import CHROMIUM, CHROMIUM_ARGS
from tests.helpers.outputs import serve

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_the_dashboard_shows_the_calibration_phase_of_a_first_start(tmp_path: Path) -> None:
    if not CHROMIUM.exists():
        pytest.skip("Chromium not installed at /usr/bin/chromium (make test installs it)")
    from playwright.sync_api import sync_playwright

    from app.main import create_app

    settings = Settings(data_dir=tmp_path, viewer=False, sim_seed=7, exposure_ms=60.0)
    with serve(create_app(settings)) as host, sync_playwright() as p:
        base = f"http://{host}"
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            pg = browser.new_page(viewport={"width": 1600, "height": 1000}, bypass_csp=True)
            pg.goto(base + "/", wait_until="load")
            pg.wait_for_function(
                "document.querySelector('#warnings').textContent.includes('⏳')", timeout=60_000)
            st = httpx.get(base + "/api/status", timeout=10).json()
            assert st["state"] == "calibrating" and st["phase"].startswith("calibrating"), st
            assert isinstance(st["progress"], float) and 0.0 <= st["progress"] <= 1.0, st
            assert pg.locator("#state").text_content() == "calibrating"
            text = pg.locator("#warnings").text_content() or ""
            shown = re.search(r"⏳ (calibrating[^(]*) \((\d+) %\)", text)
            assert shown is not None, text
            assert "calibrating: calibrating" not in text, text  # the state said once
            assert not pg.locator("#warnings").is_hidden()
        finally:
            browser.close()
