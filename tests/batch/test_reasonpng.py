"""``reason.png`` as a palette PNG: two PNG readers decode the same RGB pixels as from the
reference RGB image of :func:`app.recon.colormap.reason_png`."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from app.batch.reasonpng import palette_png_bytes, reason_png_indexed
from app.core.reasons import Reason
from app.recon import reason_png


def _maps() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    blocks = np.zeros((1032, 1384), np.uint8)
    blocks[200:600, 300:900] = Reason.LOW_MODULATION
    blocks[700:, :100] = Reason.OUTSIDE_VOLUME
    blocks[rng.random(blocks.shape) < 0.02] = Reason.UNCERTAIN
    blocks[900:950, 1000:1300] = Reason.MOTION
    return {
        "camera-sized blocks": blocks,
        "every code, noise": rng.integers(0, 9, (480, 640)).astype(np.uint8),
        "unknown codes": rng.integers(0, 12, (100, 300)).astype(np.uint8),
        "int16 beyond 0..255": rng.integers(-3, 300, (50, 60)).astype(np.int16),
        "narrower than the legend": np.full((10, 10), Reason.MOTION, np.uint8),
        "all ok": np.zeros((30, 40), np.uint8),
        # the longest legend line (100.0 % of the longest name), on canvases about its width
        "longest label, wide": np.full((20, 400), Reason.UNWRAP_INCONSISTENT, np.uint8),
        "longest label, 231 px": np.full((20, 231), Reason.UNWRAP_INCONSISTENT, np.uint8),
        "longest label, 200 px": np.full((20, 200), Reason.UNWRAP_INCONSISTENT, np.uint8),
    }


@pytest.mark.parametrize("name", list(_maps()))
def test_readers_get_the_reference_pixels(name):
    reason = _maps()[name]
    data = reason_png_indexed(reason)
    expected = cv2.imdecode(np.frombuffer(reason_png(reason), np.uint8), cv2.IMREAD_COLOR)
    by_opencv = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    with Image.open(io.BytesIO(data)) as img:
        assert img.mode == "P"  # the palette image, not the RGB fallback
        by_pillow = np.asarray(img.convert("RGB"))[..., ::-1]
    assert by_opencv.shape == expected.shape
    np.testing.assert_array_equal(by_opencv, expected)
    np.testing.assert_array_equal(by_pillow, expected)


def test_the_palette_image_is_smaller_than_the_rgb_one():
    reason = _maps()["camera-sized blocks"]
    assert len(reason_png_indexed(reason)) < len(reason_png(reason))


def test_bad_arrays_name_the_argument():
    with pytest.raises(ValueError, match="^reason"):
        reason_png_indexed(np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="^rows"):
        palette_png_bytes(np.zeros((2, 1), np.uint8), np.zeros((1, 3), np.uint8))
    with pytest.raises(ValueError, match="^palette"):
        palette_png_bytes(np.zeros((2, 3), np.uint8), np.zeros((257, 3), np.uint8))


_DECODE_JS = """async (b64) => {
    const bytes = Uint8Array.from(atob(b64), c => c.charCodeAt(0));
    const bitmap = await createImageBitmap(new Blob([bytes], {type: "image/png"}),
                                           {colorSpaceConversion: "none"});
    const canvas = new OffscreenCanvas(bitmap.width, bitmap.height);
    const ctx = canvas.getContext("2d");
    ctx.drawImage(bitmap, 0, 0);
    const rgba = ctx.getImageData(0, 0, bitmap.width, bitmap.height).data;
    let text = "";
    for (let i = 0; i < rgba.length; i += 8192) {
        text += String.fromCharCode.apply(null, rgba.subarray(i, i + 8192));
    }
    return [bitmap.width, bitmap.height, btoa(text)];
}"""


def test_a_browser_gets_the_reference_pixels():
    """Chromium's own PNG decoder (a user opening reason.png) draws the reference image."""
    import base64

    from tests.helpers.dashboard import CHROMIUM, CHROMIUM_ARGS

    if not CHROMIUM.exists():
        pytest.skip("Chromium not installed at /usr/bin/chromium (make test installs it)")
    from playwright.sync_api import sync_playwright

    reason = _maps()["unknown codes"]
    expected = cv2.imdecode(np.frombuffer(reason_png(reason), np.uint8), cv2.IMREAD_COLOR)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page()
            width, height, data = page.evaluate(
                _DECODE_JS, base64.b64encode(reason_png_indexed(reason)).decode())
        finally:
            browser.close()
    rgba = np.frombuffer(base64.b64decode(data), np.uint8).reshape(height, width, 4)
    assert (rgba[..., 3] == 255).all()
    np.testing.assert_array_equal(rgba[..., 2::-1], expected)
