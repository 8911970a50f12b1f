"""The CFPE real captures (MIT licence, see its README): where they lie and how they read.

Four scenes, 640 × 480 8-bit, fringe periods of 48, 45 and 42 of the projector's 1920
pixels, 12 steps each. The folder is ``FRINGESCOPE_CFPE_DIR``, default
``<repo>/../shared/data/cfpe``; tests skip where it is absent.
"""

from __future__ import annotations

import os
from functools import cache
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from app.recon import PatternSchedule
from app.recon.phase import wrapped_phase

CFPE = Path(os.environ.get("FRINGESCOPE_CFPE_DIR",
                           Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "cfpe"))
PERIODS_PX = (48, 45, 42)  # ascending fringe count; the files' period index is 2, 1, 0
FREQS = tuple(1920 / p for p in PERIODS_PX)
PLATE, CLOTH, BUST, BOTTLE = 1, 4, 6, 8


def schedule(steps: int) -> PatternSchedule:
    return PatternSchedule(frequencies=FREQS, steps=steps, width=1920, height=1080,
                           unwrap="heterodyne")


@cache
def frames(scene: int, steps: int) -> npt.NDArray[np.uint8]:
    """(3·steps, 480, 640) uint8 in capture-set order; ``steps`` = 12 or an even subset of it."""
    picks = range(0, 12, 12 // steps)
    out = []
    for period in PERIODS_PX:
        index = {42: 0, 45: 1, 48: 2}[period]
        for s in picks:
            path = CFPE / "recordings" / f"{scene:02d}{12 * index + s:02d}.png"
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            assert img is not None and img.dtype == np.uint8 and img.ndim == 2
            out.append(img)
    return np.stack(out)


@cache
def usable(scene: int) -> npt.NDArray[np.bool_]:
    """The issue's denominator: 12-step modulation ≥ 10 codes in every period, no clipped sample."""
    f = frames(scene, 12)
    wp = wrapped_phase(f, 12)
    return (wp.modulation.min(axis=0) >= 10.0) & ~(f >= 255).any(axis=0)
