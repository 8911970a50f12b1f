"""The dashboard in headless Chromium against the real app on the simulator.

One uvicorn server (create_app on the simulator) and one page for the module: the page
loads without console errors, the depth image changes, the exposure slider reaches
/api/status, the 3-D view draws the point cloud; a screenshot is kept in
test-artifacts/dashboard.png.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from app.recon.colormap import depth_colormap
from tests.helpers.outputs import wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"


def _canvas_png(pg: Any, selector: str) -> bytes:
    url = pg.evaluate(f"document.querySelector('{selector}').toDataURL('image/png')")
    import base64

    return base64.b64decode(url.split(",", 1)[1])


def test_page_loads_without_console_errors(page: tuple[Any, list[str]], server: str) -> None:
    pg, errors = page
    assert pg.title() == "Fringescope"
    pg.wait_for_function(
        "document.querySelector('#state').textContent === 'running'", timeout=30_000
    )
    # The status bar shows the figures of /api/status.
    for sel in ("#m-camera", "#m-depth", "#m-dropped", "#m-incomplete"):
        assert float(pg.text_content(sel) or "nan") >= 0, sel
    assert pg.text_content("#m-mode") == "set"
    assert pg.locator("#devices .chip").count() == 3
    assert pg.is_hidden("#fault")
    assert errors == []


def test_depth_image_changes_over_time(page: tuple[Any, list[str]]) -> None:
    pg, errors = page
    shown0 = pg.evaluate("window.fringescope.framesShown")
    img0 = _canvas_png(pg, "#depth")
    # The next depth map (the simulator is real-time: slow on a busy machine).
    pg.wait_for_function(f"window.fringescope.framesShown >= {shown0 + 1}", timeout=180_000)
    # the counter moves when an image arrives; the canvas is painted once it has decoded
    deadline = time.monotonic() + 60.0
    img1 = _canvas_png(pg, "#depth")
    while img1 == img0 and time.monotonic() < deadline:
        pg.wait_for_timeout(250)
        img1 = _canvas_png(pg, "#depth")
    assert img0 != img1
    assert pg.evaluate("window.fringescope.streamKind") == "stream"  # the WebSocket, not polling
    # The canvas holds the depth part only, at the sensor's aspect ratio, TURBO-coloured.
    w, h = pg.evaluate(
        "[document.querySelector('#depth').width, document.querySelector('#depth').height]"
    )
    sw, sh = pg.evaluate("window.fringescope.sensor")
    assert abs(w / h - sw / sh) < 0.02
    rgb = cv2.imdecode(np.frombuffer(img1, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].reshape(-1, 3)
    lut = depth_colormap(np.arange(256, dtype=np.float32)[None, :], (0.0, 255.0))[0].astype(int)
    colored = rgb[rgb.max(axis=1) > 40].astype(int)
    assert len(colored) > 0.2 * len(rgb)
    sample = colored[:: max(1, len(colored) // 2000)]
    dist = np.abs(sample[:, None, :] - lut[None, :, :]).sum(axis=2).min(axis=1)
    assert np.median(dist) < 25  # JPEG-compressed TURBO colours
    assert errors == []


def test_3d_view_renders_points(page: tuple[Any, list[str]], server: str) -> None:
    pg, errors = page
    frame = pg.frame_locator("#viewer3d")
    canvas = frame.locator("canvas").first
    canvas.wait_for(state="visible", timeout=60_000)
    lut = depth_colormap(np.arange(256, dtype=np.float32)[None, :], (0.0, 255.0))[0].astype(int)

    def turbo_fraction() -> float:
        png = canvas.screenshot()
        rgb = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].reshape(-1, 3)
        rgb = rgb[:: max(1, len(rgb) // 20000)].astype(int)
        saturated = rgb[(rgb.max(axis=1) - rgb.min(axis=1)) > 60]
        if len(saturated) == 0:
            return 0.0
        dist = np.abs(saturated[:, None, :] - lut[None, :, :]).sum(axis=2).min(axis=1)
        return float((dist < 40).sum()) / len(rgb)

    # Points arrive over the relayed WebSocket and are drawn with the TURBO colours.
    deadline = time.monotonic() + 60
    fraction = turbo_fraction()
    while fraction < 0.02 and time.monotonic() < deadline:
        pg.wait_for_timeout(1000)
        fraction = turbo_fraction()
    assert fraction >= 0.02, f"only {fraction:.3%} of the 3-D view is point-cloud coloured"
    assert errors == []


def test_controls_take_their_ranges_from_the_limits_route(
    page: tuple[Any, list[str]], server: str
) -> None:
    """The LED choices, exposure range and colour range come from GET /api/limits (not the page)."""
    pg, errors = page
    limits = httpx.get(f"{server}/api/limits").json()
    pg.wait_for_function("window.fringescope.limits !== null", timeout=10_000)
    leds = pg.evaluate("[...document.querySelectorAll('#led option')].map(o => o.value)")
    assert leds == limits["leds"]
    lo, hi = pg.evaluate("[Number(document.querySelector('#exposure').min), "
                         "Number(document.querySelector('#exposure').max)]")
    assert [lo, hi] == limits["exposure_ms"]
    assert pg.evaluate("window.fringescope.range") == limits["depth_range_mm"]
    assert errors == []


def test_exposure_slider_reaches_status(page: tuple[Any, list[str]], server: str) -> None:
    pg, errors = page
    before = httpx.get(f"{server}/api/status").json()["exposure_ms"]
    target = 37 if round(before) != 37 else 41
    pg.locator("#exposure").fill(str(target))
    assert pg.text_content("#exposure-value") == str(target)
    ok = wait_for(
        lambda: httpx.get(f"{server}/api/status").json()["exposure_ms"] == target, 10, 0.2
    )
    assert ok, httpx.get(f"{server}/api/status").json()["exposure_ms"]
    assert errors == []


def test_schedule_selector_lists_predictions_and_switches(
    page: tuple[Any, list[str]], server: str
) -> None:
    """The selector shows every registered schedule with its predicted σ and order-error rate;
    choosing one reaches the status, and the schedule line follows."""
    pg, errors = page
    rows = httpx.get(f"{server}/api/schedules").json()
    pg.wait_for_function("document.querySelectorAll('#schedule option').length > 0", timeout=10_000)
    options = pg.evaluate(
        "[...document.querySelectorAll('#schedule option')].map(o => [o.value, o.textContent])"
    )
    assert [v for v, _ in options] == [r["name"] for r in rows]
    assert all("frames" in text and "order err" in text and "σ" in text for _, text in options)
    try:
        pg.select_option("#schedule", "geometric-9")
        ok = wait_for(
            lambda: httpx.get(f"{server}/api/status").json()["schedule"]["name"] == "geometric-9",
            20,
            0.2,
        )
        assert ok, httpx.get(f"{server}/api/status").json()["schedule"]
        pg.wait_for_function(
            "document.querySelector('#schedule-line').textContent.includes('[1, 6, 36] × 3')",
            timeout=10_000,
        )
    finally:
        # builds an engine, waits a set
        httpx.put(f"{server}/api/schedule", json={"name": "paper-16"}, timeout=30)
        assert wait_for(
            lambda: len(httpx.get(f"{server}/api/result/latest").json()["frame_indices"]) == 16,
            60,
            0.2,
        )
    assert errors == []


def test_roi_drag_maps_to_sensor_pixels_and_measures(page: tuple[Any, list[str]]) -> None:
    pg, errors = page
    pg.evaluate("window.scrollTo(0, 0)")  # earlier tests may have scrolled to the controls
    box = pg.locator("#roi").bounding_box()
    assert box is not None
    sw, sh = pg.evaluate("window.fringescope.sensor")
    x0, y0 = box["x"] + 0.25 * box["width"], box["y"] + 0.30 * box["height"]
    x1, y1 = box["x"] + 0.55 * box["width"], box["y"] + 0.70 * box["height"]
    with pg.expect_request(lambda r: r.url.endswith("/api/analysis/plane")) as req:
        pg.mouse.move(x0, y0)
        pg.mouse.down()
        pg.mouse.move((x0 + x1) / 2, (y0 + y1) / 2, steps=4)
        pg.mouse.move(x1, y1, steps=4)
        pg.mouse.up()
    roi = req.value.post_data_json["roi"]
    # Display position → sensor pixels (the canvas is scaled to fit the panel).
    expected = [0.25 * sw, 0.30 * sh, 0.55 * sw, 0.70 * sh]
    assert all(abs(a - b) <= 0.01 * sw + 2 for a, b in zip(roi, expected, strict=True)), (
        roi,
        expected,
    )
    pg.wait_for_function("!document.querySelector('#roi-result').textContent.startsWith('measuring')",
                         timeout=60_000)
    text = pg.text_content("#roi-result") or ""
    assert "accuracy" in text and "precision" in text and "points" in text, text
    assert errors == []


def test_record_button_records_and_lists(page: tuple[Any, list[str]], server: str) -> None:
    pg, errors = page
    pg.fill("#record-name", "browser_take")
    pg.click("#btn-record")
    assert wait_for(
        lambda: httpx.get(f"{server}/api/status").json().get("recording") == "browser_take", 15, 0.2
    )
    pg.wait_for_function(
        "document.querySelector('#btn-record').textContent.includes('Stop')", timeout=15_000
    )
    pg.wait_for_timeout(3000)  # let at least one set be written
    pg.click("#btn-record")
    assert wait_for(
        lambda: httpx.get(f"{server}/api/status").json().get("recording") is None, 30, 0.2
    )
    pg.wait_for_function(
        "[...document.querySelectorAll('#recordings a')]"
        ".some(a => a.textContent.startsWith('browser_take'))",
        timeout=15_000,
    )
    names = [r["name"] for r in httpx.get(f"{server}/api/recordings").json()]
    assert "browser_take" in names
    assert errors == []


def test_screenshot_artifact(page: tuple[Any, list[str]]) -> None:
    pg, errors = page
    ARTIFACTS.mkdir(exist_ok=True)
    pg.wait_for_timeout(1500)
    path = ARTIFACTS / "dashboard.png"
    pg.screenshot(path=str(path), full_page=True)
    img = cv2.imread(str(path))
    assert img is not None and img.shape[1] == 1600
    assert errors == []
