"""Small recordings (capture-set folders) with known frame values, for the replay camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.capture.captureset import CaptureSet, write_capture_set

H, W, N = 12, 10, 16


def make_recording(root: Path, n_sets: int = 2, timestamps: bool = False,
                   exposure_ms: float = 20.0) -> Path:
    """Sets whose frame j of set s is uniform with value 16·s + j (+ timestamps 30 ms apart)."""
    for s in range(n_sets):
        frames = np.stack([np.full((H, W), 16 * s + j, np.uint8) for j in range(N)])
        stamps = [1000.0 + 0.5 * s + 0.030 * j for j in range(N)]
        extra = {"timestamps_s": stamps} if timestamps else {}
        write_capture_set(root / f"set_{s:04d}",
                          CaptureSet(frames=frames, exposure_ms=exposure_ms, extra=extra))
    return root
