"""The dashboard stays put: live updates never move the depth image (headless Chromium).

One uvicorn server (create_app on the simulator) for the module; per page width (1280, 1600
and 1920 px) a fresh page: the depth canvas's bounding box, and every status-bar field's,
is sampled for 10 s of live updates and must not move; then the status fields are given
their narrowest and widest texts, a warning and a fault, and still nothing moves. In σ mode
the colour bar shows the σ range in mm (not the 0–35 mm height ticks).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.helpers.dashboard import CHROMIUM, CHROMIUM_ARGS, live_server

pytestmark = [pytest.mark.browser, pytest.mark.slow]

WATCH_S = 10.0
TOLERANCE_PX = 0.5

BOX_JS = """sel => [...document.querySelectorAll(sel)].map(e => {
  const r = e.getBoundingClientRect();
  return [Math.round(r.x * 100) / 100, Math.round(r.y * 100) / 100,
          Math.round(r.width * 100) / 100, Math.round(r.height * 100) / 100];
})"""
WATCHED = "#depth, #statusbar, #statusbar > *, #warnings, .depth-panel .panel-head"


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> Iterator[str]:
    with live_server(tmp_path_factory, request, "layout-data", viewer=False) as base:
        yield base


@pytest.fixture(scope="module")
def browser(server: str) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def open_page(browser: Any, server: str, width: int) -> Any:
    # Playwright polls wait_for_function with eval, which the dashboard's CSP blocks;
    # tests/browser/test_csp.py keeps the CSP on
    pg = browser.new_page(viewport={"width": width, "height": 1000}, bypass_csp=True)
    pg.goto(server + "/", wait_until="load")
    # live: a depth image drawn (the canvas takes the sensor's aspect) and the status polled
    pg.wait_for_function(
        "window.fringescope.framesShown >= 1 && window.fringescope.status", timeout=120_000
    )
    pg.wait_for_timeout(1500)  # the colour range from /api/limits, a second status
    return pg


def boxes(pg: Any) -> list[list[float]]:
    return pg.evaluate(BOX_JS, WATCHED)  # type: ignore[no-any-return]


def moved(before: list[list[float]], after: list[list[float]]) -> float:
    """Largest change of any coordinate, px (inf if elements came or went)."""
    if len(before) != len(after):
        return float("inf")
    return max(
        abs(a - b)
        for ba, bb in zip(before, after, strict=True)
        for a, b in zip(ba, bb, strict=True)
    )


@pytest.mark.parametrize("width", [1280, 1600, 1920])
def test_depth_image_does_not_move_over_live_updates(browser: Any, server: str, width: int) -> None:
    pg = open_page(browser, server, width)
    try:
        errors: list[str] = []
        pg.on("pageerror", lambda exc: errors.append(str(exc)))
        first = boxes(pg)
        frames0 = pg.evaluate("window.fringescope.framesShown")
        texts = set()
        worst = 0.0
        t_end = time.monotonic() + WATCH_S
        while time.monotonic() < t_end:
            worst = max(worst, moved(first, boxes(pg)))
            texts.add(pg.text_content("#statusbar") + "|" + pg.text_content("#depth-info"))
            pg.wait_for_timeout(100)
        frames = pg.evaluate("window.fringescope.framesShown") - frames0
        assert frames >= 2, f"only {frames} depth images in {WATCH_S} s: not a live page"
        assert len(texts) >= 3, "the status texts did not change: nothing was updated"
        assert worst <= TOLERANCE_PX, (
            f"at {width} px the layout moved by {worst:.1f} px during live updates"
        )

        # every status field at its narrowest and its widest, a warning, a fault: still put
        for value, state in (("0", "stopped"), ("88888.8", "calibrating"), ("–", "fault")):
            pg.evaluate(
                """([value, state]) => {
                  for (const id of ["m-camera", "m-depth", "m-latency", "m-dropped",
                                    "m-incomplete"])
                    document.getElementById(id).textContent = value;
                  document.getElementById("m-mode").textContent = value === "0" ? "set" : "rolling";
                  document.getElementById("m-sensor").textContent =
                    value === "0" ? "8-bit"
                                  : "16-bit · heterodyne [1, 4.25, 12.5, 36.75]×12 horizontal";
                  document.getElementById("state").textContent = state;
                  const w = document.getElementById("warnings");
                  w.hidden = value === "0";
                  w.textContent = "⚠ camera: frames dropped ".repeat(value === "0" ? 0 : 20);
                  document.getElementById("fault").hidden = state !== "fault";
                  document.getElementById("fault-text").textContent = "camera: ".repeat(30);
                  document.getElementById("depth-info").textContent =
                    value === "0" ? "1 images" : "123456 images · last 1234.5 s ago";
                }""",
                [value, state],
            )
            worst = moved(first, boxes(pg))
            assert worst <= TOLERANCE_PX, (
                f"at {width} px status texts {value!r}/{state!r} moved the layout {worst:.1f} px"
            )
        assert errors == []
    finally:
        pg.close()


def tick_values(pg: Any) -> list[float]:
    return [
        float(t)
        for t in pg.evaluate(
            "[...document.querySelectorAll('#bar-ticks .tick')].map(t => t.textContent)"
        )
    ]


def test_sigma_mode_shows_a_sigma_colour_bar_in_mm(browser: Any, server: str) -> None:
    limits = httpx.get(f"{server}/api/limits").json()
    lo, hi = limits["depth_range_mm"]
    pg = open_page(browser, server, 1600)
    try:
        assert pg.text_content("#bar-title") == "height, mm"
        height_ticks = tick_values(pg)
        assert height_ticks[0] == lo and hi - 10 < height_ticks[-1] <= hi, height_ticks
        first = boxes(pg)
        with pg.expect_response(lambda r: "field=sigma" in r.url, timeout=30_000) as resp:
            pg.check("#show-sigma")
        url = resp.value.url
        assert resp.value.status == 200 and "min_mm=0&" in url and url.endswith("max_mm=0.1"), url
        assert pg.text_content("#bar-title") == "σ, mm"
        ticks = tick_values(pg)
        assert ticks[0] == 0.0 and ticks[-1] == pytest.approx(0.1) and len(ticks) >= 3, ticks
        assert all(b > a for a, b in zip(ticks, ticks[1:], strict=False)), ticks
        assert [pg.input_value("#range-min"), pg.input_value("#range-max")] == ["0", "0.1"]
        # the σ map is drawn (polled) and the image stays where it was
        shown = pg.evaluate("window.fringescope.framesShown")
        pg.wait_for_function(f"window.fringescope.framesShown > {shown}", timeout=30_000)
        assert pg.evaluate("window.fringescope.streamKind") == "poll"
        assert moved(first, boxes(pg)) <= TOLERANCE_PX
        # a σ range typed in is the one asked for and shown
        with pg.expect_response(
            lambda r: "field=sigma" in r.url and "max_mm=0.05" in r.url, timeout=30_000
        ):
            pg.fill("#range-max", "0.05")
            pg.dispatch_event("#range-max", "change")
        assert tick_values(pg)[-1] == pytest.approx(0.05)
        assert pg.evaluate("window.fringescope.range") == [lo, hi]  # the height range is kept
        # back to height: the image is fetched at once in the height range, whatever the stream does
        with pg.expect_response(lambda r: "format=color" in r.url and "field=sigma" not in r.url,
                                timeout=30_000) as back:
            pg.uncheck("#show-sigma")
        assert f"max_mm={hi:g}" in back.value.url, back.value.url
        assert pg.text_content("#bar-title") == "height, mm"
        assert tick_values(pg) == height_ticks
        assert [float(pg.input_value("#range-min")), float(pg.input_value("#range-max"))] == [
            lo,
            hi,
        ]
        assert moved(first, boxes(pg)) <= TOLERANCE_PX
    finally:
        pg.close()
