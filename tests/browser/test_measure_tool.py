"""The dashboard's measure tool in headless Chromium: click two points on the depth image, read the
length ± σ, and compare it with POST /api/measure on the same pixels."""

from __future__ import annotations

from typing import Any

import httpx
import pytest

from tests.helpers.outputs import wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_click_two_points_reads_the_length(page: tuple[Any, list[str]], server: str) -> None:  # noqa: F811
    pg, errors = page
    # hold the depth map still
    assert httpx.post(f"{server}/api/acquisition/stop").status_code == 200
    try:
        pg.wait_for_timeout(1500)
        pg.evaluate("window.scrollTo(0, 0)")
        pg.select_option("#measure-kind", "length")
        box = pg.locator("#roi").bounding_box()
        assert box is not None
        sw, sh = pg.evaluate("window.fringescope.sensor")
        with pg.expect_response(
            lambda r: r.url.endswith("/api/measure") and r.request.method == "POST"
        ) as resp:
            pg.mouse.click(box["x"] + 0.35 * box["width"], box["y"] + 0.40 * box["height"])
            pg.mouse.click(box["x"] + 0.60 * box["width"], box["y"] + 0.55 * box["height"])
        assert resp.value.status == 200, resp.value.text()
        pg.wait_for_function(
            "document.querySelector('#measure-result').dataset.value !== undefined", timeout=30_000
        )
        shown = pg.text_content("#measure-value") or ""
        value = float(pg.get_attribute("#measure-result", "data-value") or "nan")
        sigma = float(pg.get_attribute("#measure-result", "data-sigma") or "nan")
        assert shown == f"{value:.3f} ± {sigma:.3f} mm", shown
        points = pg.evaluate("window.fringescope.measure.points")
        # display position → sensor pixels
        assert (
            abs(points[0][0] - 0.35 * sw) <= 0.01 * sw + 2
            and abs(points[1][1] - 0.55 * sh) <= 0.01 * sh + 2
        )
        r = httpx.post(f"{server}/api/measure", json={"kind": "length", "points": points})
        assert r.status_code == 200, r.text
        assert r.json()["value_mm"] == pytest.approx(value, rel=1e-9)
        assert r.json()["sigma_mm"] == pytest.approx(sigma, rel=1e-9) and sigma > 0
        # the measurement is kept for recordings, and drawn beside the line
        kept = httpx.get(f"{server}/api/measure/tool").json()["measurements"]
        assert kept and kept[0]["kind"] == "length" and kept[0]["points"] == points
        drawn = pg.evaluate("""(() => { const c = document.querySelector('#measure');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; })()""")
        assert drawn > 200
        pg.click("#measure-clear")
        pg.select_option("#measure-kind", "")
        assert wait_for(
            lambda: httpx.get(f"{server}/api/measure/tool").json()["measurements"] == [], 10, 0.1
        )
        assert errors == []
    finally:
        httpx.post(f"{server}/api/acquisition/start")


def test_a_refused_measurement_is_shown_once_not_reposted(
        page: tuple[Any, list[str]], server: str) -> None:  # noqa: F811
    pg, errors = page
    posts: list[int] = []
    pg.on("response", lambda r: posts.append(r.status)
          if r.url.endswith("/api/measure") and r.request.method == "POST" else None)
    pg.evaluate("window.scrollTo(0, 0)")
    pg.select_option("#measure-kind", "area")
    box = pg.locator("#roi").bounding_box()
    assert box is not None
    for fx in (0.3, 0.4, 0.5):  # three points on one line: a polygon that encloses nothing
        pg.mouse.click(box["x"] + fx * box["width"], box["y"] + 0.5 * box["height"])
    before = pg.evaluate("window.fringescope.measure.posts")
    pg.click("#measure-done")
    pg.wait_for_function("document.querySelector('#measure-result').classList.contains('error')",
                         timeout=30_000)
    text = pg.text_content("#measure-result") or ""
    assert "encloses less than one pixel" in text and "not measured again" in text, text
    seq = httpx.get(f"{server}/api/status").json()["results_published"]
    status = f"{server}/api/status"
    assert wait_for(lambda: httpx.get(status).json()["results_published"] >= seq + 4, 60, 0.2)
    pg.wait_for_timeout(1500)  # the page has seen the new maps (status is polled)
    assert posts == [422], posts  # posted once, not once per new depth map
    assert pg.evaluate("window.fringescope.measure.posts") == before + 1
    assert sum("422" in e for e in errors) <= 1  # the browser logs the one refused request, no more
    errors[:] = [e for e in errors if "422" not in e]
    # a new click starts afresh: a proper polygon is measured again on every map
    for fx, fy in ((0.35, 0.35), (0.6, 0.35), (0.6, 0.6), (0.35, 0.6)):
        pg.mouse.click(box["x"] + fx * box["width"], box["y"] + fy * box["height"])
    before = pg.evaluate("window.fringescope.measure.posts")
    pg.click("#measure-done")
    pg.wait_for_function("document.querySelector('#measure-result').dataset.coverage !== undefined",
                         timeout=30_000)
    # measured again on the next maps (the page's own count of posts), and never refused
    pg.wait_for_function(f"window.fringescope.measure.posts >= {before + 2}", timeout=60_000)
    pg.wait_for_timeout(1000)  # let the last answers arrive
    assert posts.count(200) >= 1 and posts.count(422) == 1, posts
    assert "error" not in (pg.get_attribute("#measure-result", "class") or "")
    pg.click("#measure-clear")
    pg.select_option("#measure-kind", "")
    assert errors == []
