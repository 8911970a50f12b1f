"""Per-pixel motion detection for rolling mode.

The background A = mean of the N shifted images of one frequency does not depend on the
fringe frequency for a still scene, so when the A of the frequencies in one set differ by
more than noise, the scene moved while the set was taken and the phase is untrustworthy.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from app.core.reasons import Reason

#: reason code for "moved during the set" (after the engine's own codes)
MOTION = int(getattr(Reason, "MOTION", max(int(r) for r in Reason) + 1))


def motion_mask(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    n_frequencies: int,
    *,
    full_scale: float,
    rel_threshold: float = 0.15,
    abs_threshold: float = 0.04,
) -> npt.NDArray[np.bool_]:
    """Pixels whose background differs between frequencies (the scene moved).

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = n_frequencies × steps.
        n_frequencies: number of fringe frequencies in the set.
        full_scale: the sensor's maximum value (255 for 8-bit, 4095 for 12-bit).
        rel_threshold: allowed spread of A as a fraction of the mean A.
        abs_threshold: allowed spread as a fraction of ``full_scale`` (the noise floor).

    Returns:
        (H, W) bool, True where max_k A_k − min_k A_k exceeds both thresholds.
    """
    if frames.ndim != 3:
        raise ValueError(f"frames: expected (F, H, W), got shape {frames.shape}")
    f, h, w = frames.shape
    if n_frequencies < 2 or f % n_frequencies:
        raise ValueError(f"n_frequencies: {n_frequencies} does not divide {f} frames")
    steps = f // n_frequencies
    # Sums of N frames in uint32 (exact, and much cheaper than float means).
    sums = frames.reshape(n_frequencies, steps, h, w).sum(axis=1, dtype=np.uint32)
    hi = sums.max(axis=0)
    lo = sums.min(axis=0)
    spread = (hi - lo).astype(np.float32) / steps
    mean_a = sums.sum(axis=0, dtype=np.float32) / (steps * n_frequencies)
    thr = np.maximum(rel_threshold * mean_a, abs_threshold * float(full_scale))
    return spread > thr
