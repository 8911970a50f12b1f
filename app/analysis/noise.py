"""Predicted noise floor of a fringe measurement: σ_φ = σ_I·√(2/N)/B through ∂z/∂φ."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from app.calib.model import height_mm
from app.core.calibration import Calibration

F64 = npt.NDArray[np.float64]


def phase_noise_rad(sigma_i: npt.ArrayLike, modulation: npt.ArrayLike, steps: int) -> F64:
    """Standard deviation (rad) of the N-step phase for intensity noise σ_I and modulation B.

    Args:
        sigma_i: intensity noise per frame, codes (scalar or (H, W)).
        modulation: modulation B, codes ((H, W)); NaN or ≤ 0 gives NaN.
        steps: phase shifts N ≥ 3.
    """
    if int(steps) != steps or steps < 3:
        raise ValueError(f"steps: need an integer N >= 3, got {steps}")
    b = np.asarray(modulation, np.float64)
    s = np.asarray(sigma_i, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(b > 0, s * math.sqrt(2.0 / steps) / b, np.nan)


def dz_dphi(calibration: Calibration, phase: npt.ArrayLike, *, step_rad: float = 1e-3) -> F64:
    """∂height/∂φ (mm/rad) of the calibration's Eq. (5) at every pixel of a (H, W) phase map."""
    phi = np.asarray(phase, np.float64)
    if phi.ndim != 2:
        raise ValueError(f"phase: expected (H, W), got shape {phi.shape}")
    if phi.shape != (calibration.image_size[1], calibration.image_size[0]):
        raise ValueError(f"phase: shape {phi.shape} does not match the calibration's image size")
    vv, uu = np.mgrid[0 : phi.shape[0], 0 : phi.shape[1]].astype(np.float64)
    hi = height_mm(calibration, uu, vv, phi + step_rad)
    lo = height_mm(calibration, uu, vv, phi - step_rad)
    return ((hi - lo) / (2 * step_rad)).reshape(phi.shape)


def height_noise_mm(calibration: Calibration, phase: npt.ArrayLike, sigma_i: npt.ArrayLike,
                    modulation: npt.ArrayLike) -> F64:
    """Predicted per-pixel height noise σ_z (mm) = |∂z/∂φ|·σ_I·√(2/N)/B (finest frequency)."""
    sig_phi = phase_noise_rad(sigma_i, modulation, calibration.pattern.steps)
    return np.abs(dz_dphi(calibration, phase)) * sig_phi
