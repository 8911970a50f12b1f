"""The standard noisy observations of the analytic rig (tests/helpers/calib_rig.py) that
several calibration tests fit: one definition, so a fit of them can be shared."""

from __future__ import annotations

import numpy as np

from app.calib.fitting import PoseObservation
from tests.helpers.calib_rig import BOARD, STANDARD_POSES, Rig, board_pose

#: corner noise per coordinate (px) of the shared noisy fit, and its generator's seed
STANDARD_NOISE_PX = 0.05
STANDARD_NOISE_SEED = 7


def standard_noisy_observations(rig: Rig) -> list[PoseObservation]:
    """The six standard poses (:data:`STANDARD_POSES`, pose 0 the reference) of :data:`BOARD`
    through ``rig``, corners with Gaussian noise of :data:`STANDARD_NOISE_PX` px drawn in pose
    order from one generator seeded :data:`STANDARD_NOISE_SEED`; phase maps (H, W) float32 rad
    noise-free."""
    rng = np.random.default_rng(STANDARD_NOISE_SEED)
    return [
        rig.observe(BOARD, *board_pose(BOARD, *p[:4], p[4]), f"pose_{i:02d}",
                    noise_px=STANDARD_NOISE_PX, rng=rng)
        for i, p in enumerate(STANDARD_POSES)
    ]
