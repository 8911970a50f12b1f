"""The dashboard's change mode in headless Chromium against the real app on the twin.

The twin shows the still tissue with a 0.3 mm bump (``tissue_bump``); the reference is an
uploaded capture set of the same tissue without it (``tissue_still``, rendered offline). The
change mode must show the bump in red on the diverging scale with its bar in mm, and the
largest rise ± σ on hover. A screenshot is kept in test-artifacts/change.png.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.capture import write_capture_set
from app.devices.sim.offline import render_capture_set
from tests.helpers.dashboard import CHROMIUM, CHROMIUM_ARGS, live_server
from tests.helpers.outputs import wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"


@pytest.fixture(scope="module")
def change_server(tmp_path_factory: pytest.TempPathFactory,
                  request: pytest.FixtureRequest) -> Iterator[str]:
    with live_server(tmp_path_factory, request, "change-data", sim_scene="tissue_bump") as base:
        yield base


def _reference_zip(tmp: Path) -> bytes:
    capture, _, _ = render_capture_set("tissue_still", seed=3, exposure_ms=60.0)
    write_capture_set(tmp / "ref", capture)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for f in sorted((tmp / "ref").iterdir()):
            zf.write(f, f.name)
    return buf.getvalue()


def _bump_pixel() -> tuple[float, float]:
    """(u, v) of the bump's crest in the camera image."""
    import cv2
    import numpy as np

    from app.core.schedule import PatternSchedule
    from app.devices.sim import default_rig
    from app.devices.sim.ideal import ideal_calibration
    from app.devices.sim.scenes.tissue import field_point, still_tissue_scene

    rig = default_rig()
    cal = ideal_calibration(rig, PatternSchedule())
    crest = field_point(still_tissue_scene(rig), 0.0, 0.0)
    uv, _ = cv2.projectPoints(crest[None], np.zeros(3), np.zeros(3), cal.camera_matrix,
                              cal.dist_coeffs)
    return float(uv[0, 0, 0]), float(uv[0, 0, 1])


def test_change_mode_shows_the_bump_and_its_rise_on_hover(change_server: str,
                                                          tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    r = httpx.post(f"{change_server}/api/reference", content=_reference_zip(tmp_path),
                   headers={"content-type": "application/zip"}, timeout=300)
    assert r.status_code == 200, r.text
    assert r.json()["source"] == {"kind": "upload"}
    assert wait_for(lambda: httpx.get(f"{change_server}/api/change/summary").status_code == 200,
                    300, 0.5)
    summary = httpx.get(f"{change_server}/api/change/summary").json()
    assert summary["mode"] == "fixed" and summary["rise_mm"] is not None
    u, v = _bump_pixel()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            pg: Any = browser.new_page(viewport={"width": 1600, "height": 1000}, bypass_csp=True)
            pg.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
            pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            pg.goto(change_server + "/", wait_until="load")
            pg.wait_for_function("window.fringescope && window.fringescope.framesShown >= 1",
                                 timeout=60_000)
            pg.check("#show-change")
            pg.wait_for_function("window.fringescope.streamKind === 'change'", timeout=60_000)
            assert pg.text_content("#bar-title") == "change Δ, mm"
            ticks = pg.eval_on_selector_all("#bar-ticks .tick",
                                            "els => els.map(e => e.textContent)")
            assert ticks == ["+1", "+0.5", "0", "-0.5", "-1"]
            # the bump's crest is red on the canvas: the diverging scale's rise side
            box = pg.eval_on_selector("#depth", "c => [c.width, c.height]")
            sensor = pg.evaluate("window.fringescope.sensor")
            x, y = int(u * box[0] / sensor[0]), int(v * box[1] / sensor[1])
            rgb = pg.evaluate(f"Array.from(document.querySelector('#depth').getContext('2d')"
                              f".getImageData({x - 2}, {y - 2}, 5, 5).data)")
            red, blue = sum(rgb[0::4]) / 25, sum(rgb[2::4]) / 25
            assert red > blue + 20, rgb
            # hovering shows the largest rise and sink with their ± σ
            rect = pg.eval_on_selector("#depth", "c => { const r = c.getBoundingClientRect(); "
                                       "return [r.left, r.top, r.width, r.height]; }")
            pg.mouse.move(rect[0] + rect[2] * u / sensor[0], rect[1] + rect[3] * v / sensor[1])
            tip = pg.text_content("#change-tip")
            assert pg.is_visible("#change-tip")
            assert "largest rise +0." in tip and "± 0.0" in tip and "mm" in tip, tip
            assert "fixed scope" in tip
            ARTIFACTS.mkdir(exist_ok=True)
            pg.screenshot(path=str(ARTIFACTS / "change.png"))
            # σ and change are exclusive modes
            pg.check("#show-sigma")
            assert not pg.is_checked("#show-change")
        finally:
            browser.close()
    assert not errors, errors
