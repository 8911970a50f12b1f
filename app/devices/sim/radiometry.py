"""Radiometry and sensor noise of the simulated rig.

Signal chain per pixel (electrons), T the transmission:
``e = exposure_ms · current · LED_flux[led] · QE[led] · T · κ · (reflectance · pattern + …) / d_p²``
— LED colour × camera spectral response × tissue reflectance per colour, the two scopes'
transmission T (≈ 7 %), inverse-square falloff from the projector pupil, exposure and LED
current. The sensor (Grasshopper3-like) adds photon shot noise (Poisson, Gaussian
approximation), read noise, an analog gain, and an 8- or 12-bit ADC with saturation:
``DN = clip(round(g·(e + n)), 0, 2^bits − 1)`` with g = gain·(2^bits − 1)/full_well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.core.limits import check_led, full_scale

# Relative LED radiant flux at full current (LightCrafter LEDs) and the mono sensor's
# quantum efficiency at each LED's wavelength (Sony ICX825-like: peaks in the green).
LED_FLUX = {"red": 0.85, "green": 1.0, "blue": 0.75}
SENSOR_QE = {"red": 0.45, "green": 0.62, "blue": 0.50}
SCOPE_TRANSMISSION = 0.07

# Diffuse reflectance per LED colour. Haemoglobin absorbs green and blue strongly, but the
# fringe *contrast* on pigmented tissue is best in green: red light scatters deep
# (large subsurface blur, washing out fine fringes), blue is absorbed; see SSS_MM.
REFLECTANCE = {
    "white": {"red": 0.85, "green": 0.85, "blue": 0.85},  # printed white / calibration board
    "black": {"red": 0.06, "green": 0.06, "blue": 0.06},  # printed black
    "grey": {"red": 0.45, "green": 0.45, "blue": 0.45},  # matte metrology objects
    "skin": {"red": 0.62, "green": 0.42, "blue": 0.30},
    "intestine": {"red": 0.55, "green": 0.30, "blue": 0.18},
    "intestine_dark": {"red": 0.38, "green": 0.16, "blue": 0.09},
    "intestine_pale": {"red": 0.68, "green": 0.48, "blue": 0.34},
    "suture": {"red": 0.10, "green": 0.08, "blue": 0.20},  # violet-dyed polyglactin
    "metal": {"red": 0.35, "green": 0.35, "blue": 0.35},
    "background": {"red": 0.02, "green": 0.02, "blue": 0.02},
    # appended last so the other materials keep their ids
    # undyed braided suture, brighter than tissue
    "suture_bright": {"red": 0.72, "green": 0.68, "blue": 0.62},
}
# Subsurface-scattering blur of the projected light (Gaussian σ, mm, per LED colour).
SSS_MM = {
    "skin": {"red": 0.45, "green": 0.12, "blue": 0.08},
    "intestine": {"red": 0.60, "green": 0.15, "blue": 0.10},
    "intestine_dark": {"red": 0.55, "green": 0.14, "blue": 0.09},
    "intestine_pale": {"red": 0.65, "green": 0.17, "blue": 0.11},
}
# Specular (wet surface) weight and Blinn–Phong exponent.
SPECULAR = {"skin": (0.15, 60.0), "intestine": (0.6, 120.0), "intestine_dark": (0.6, 120.0),
            "intestine_pale": (0.6, 120.0), "metal": (1.5, 30.0), "suture": (0.1, 40.0),
            "suture_bright": (0.1, 40.0)}

MATERIALS = tuple(REFLECTANCE)


def material_id(name: str) -> int:
    return MATERIALS.index(name)


@dataclass(frozen=True)
class SensorModel:
    """Mono CCD: full well, read noise (e⁻), dark+stray light rate (e⁻/ms), ADC bits."""

    full_well_e: float = 16000.0
    read_noise_e: float = 12.0
    ambient_e_per_ms: float = 3.0
    # κ: electrons per ms for reflectance 1, pattern 1, unit LED/QE/transmission at 1 mm (d_p²
    # scaled).
    photons_scale: float = 3.7e7

    def dn_per_electron(self, bits: int, gain: float) -> float:
        return gain * full_scale(bits) / self.full_well_e

    def light_scale(self, *, exposure_ms: float, current: float, led: str) -> float:
        """Electrons per (reflectance · pattern / d_p²[mm²]) for these settings."""
        check_led(led)
        return (exposure_ms * current * LED_FLUX[led] * SENSOR_QE[led] * SCOPE_TRANSMISSION
                * self.photons_scale)

    def noise_sigma(self, mean_dn: npt.ArrayLike, *, bits: int = 8,
                    gain: float = 1.0) -> npt.NDArray[np.float64]:
        """Temporal noise σ (DN) of a pixel whose noise-free mean is ``mean_dn`` (DN, before
        clipping).

        σ² = g·mean + (g·read)² + 1/12 (shot noise, read noise, ADC quantisation).
        """
        g = self.dn_per_electron(bits, gain)
        m = np.asarray(mean_dn, np.float64)
        return np.sqrt(g * np.maximum(m, 0.0) + (g * self.read_noise_e) ** 2 + 1.0 / 12.0)


def gaussian_quantile_table(n: int = 65536) -> npt.NDArray[np.float32]:
    """Φ⁻¹((i + ½)/n), i = 0..n−1, renormalised to unit variance: a 16-bit-index normal table."""
    from scipy.special import ndtri

    q: npt.NDArray[np.float64] = ndtri((np.arange(n, dtype=np.float64) + 0.5) / n)
    q /= math.sqrt(np.mean(q * q))
    return q.astype(np.float32)


def projector_response_lut(gamma: float = 1.0, black: float = 0.002) -> npt.NDArray[np.float32]:
    """Relative DMD light output for the 256 pattern levels: black + (1 − black)·(L/255)^γ."""
    if not (gamma > 0):
        raise ValueError(f"gamma: must be positive, got {gamma}")
    lv = np.arange(256, dtype=np.float64) / 255.0
    return (black + (1.0 - black) * lv**gamma).astype(np.float32)


def defocus_sigma_px(z_mm: npt.ArrayLike, focus_mm: float,
                     blur_per_inv_mm: float) -> npt.NDArray[np.float64]:
    """Gaussian σ (px) of a thin-lens blur disc of diameter blur_per_inv_mm·|1/z − 1/focus|."""
    z = np.asarray(z_mm, np.float64)
    return 0.5 * blur_per_inv_mm * np.abs(1.0 / z - 1.0 / focus_mm)
