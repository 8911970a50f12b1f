"""Limits and defaults of the instrument written once: LEDs, exposure, bit depths, depth range.

Devices, the service, the API schemas, the command line, the simulator and the page
(through ``GET /api/limits``) read them from here.
"""

from __future__ import annotations

import math
from typing import Literal

#: projector LEDs (the DLP3000 LightCrafter's), in wavelength order
LEDS: tuple[str, ...] = ("red", "green", "blue")
Led = Literal["red", "green", "blue"]
#: the LED lit when nothing else is asked for (settings, devices, capture sets without one)
DEFAULT_LED: Led = "green"

#: camera exposure per frame accepted anywhere, ms (inclusive)
EXPOSURE_RANGE_MS: tuple[float, float] = (1.0, 100.0)
#: camera exposure per frame when nothing else is asked for, ms
DEFAULT_EXPOSURE_MS = 20.0

#: the height colour range of depth pictures when none is given, mm (low, high)
DEFAULT_DEPTH_RANGE_MM: tuple[float, float] = (0.0, 35.0)

#: bit depths a capture set may declare (``"bit_depth"``; values above 2**bit_depth − 1 are refused)
CAPTURE_BIT_DEPTHS: tuple[int, ...] = (8, 10, 12, 14, 16)
#: colour channels a capture set may name for colour frames (``"channel"``)
CHANNELS: tuple[str, ...] = ("red", "green", "blue", "luminance")

#: bit depths the live camera can be configured to
LIVE_BIT_DEPTHS: tuple[int, ...] = (8, 12)
BitDepth = Literal[8, 12]


def full_scale(bit_depth: int) -> int:
    """The largest code a ``bit_depth``-bit sensor delivers, ``2**bit_depth − 1`` (255 at 8 bits).

    Raises:
        ValueError: ``bit_depth`` is not an integer within 1–16.
    """
    if isinstance(bit_depth, bool) or not isinstance(bit_depth, int) or not 1 <= bit_depth <= 16:
        raise ValueError(f"bit_depth: must be an integer within 1–16, got {bit_depth!r}")
    return (1 << bit_depth) - 1


def check_exposure_ms(exposure_ms: float) -> float:
    """``exposure_ms`` as float; ``ValueError`` naming the argument unless within
    :data:`EXPOSURE_RANGE_MS`."""
    lo, hi = EXPOSURE_RANGE_MS
    try:
        value = math.nan if isinstance(exposure_ms, str | bytes | bool) else float(exposure_ms)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"exposure_ms: must be within {lo:g}–{hi:g} ms, got {exposure_ms}")
    return value


def check_led(led: str) -> str:
    """``led`` unchanged; ``ValueError`` naming the argument unless one of :data:`LEDS`."""
    if led not in LEDS:
        raise ValueError(f"led: must be one of {LEDS}, got {led!r}")
    return led
