"""A length measured on a reconstruction with its calibration's covariance (σ_model)."""

from __future__ import annotations

from collections.abc import Sequence

from app.analysis import measure as M
from app.core.calibration import Calibration
from app.recon.reconstructor import ReconResult


def calibrated_length(res: ReconResult, cal: Calibration,
                      pixels: Sequence[tuple[int, int]]) -> M.Measurement:
    """``measure.length`` between two (u, v) pixels of ``res``: the noise part from its
    ``sigma_noise``, the calibration part from ``cal``'s jackknife, lengths in the plane of
    ``cal``'s reference normal."""
    return M.length(res.points, res.valid, res.sigma_noise, list(pixels),
                    plane_normal=cal.plane_normal, calibration=cal)
