"""Real MJPG video files written with cv2.VideoWriter, one grey level per frame."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

W, H, N = 96, 64, 16


def frame_level(k: int) -> int:
    return 20 + 13 * k  # distinct grey level per frame, 20..215


def write_video(path: Path, n: int = N, fps: float = 100.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert writer.isOpened()
    for k in range(n):
        img = np.full((H, W, 3), frame_level(k), np.uint8)
        # some colour, so mono conversion matters
        img[:, :, 2] = np.uint8(min(255, frame_level(k) + 20))
        writer.write(img)
    writer.release()
    return path
