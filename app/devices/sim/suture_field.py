"""Seeded random suture conditions: analytic height maps of a thread of known height on tissue,
as the reconstruction sees them (the suture estimator's oracle, app.analysis.feature).

A round thread of diameter d lies on curved, tilted tissue; its crest stands d above the tissue
under it. The camera's blur mixes neighbouring pixels' fringes before the phase is computed:
for the small phase differences across a blur spot the reconstructed height is their mean
weighted by the blur kernel times each pixel's fringe amplitude (∝ its albedo), so the crest is
flattened, a dark thread is pulled toward the tissue at its edges and a bright one spills onto
it. The depth noise scales with 1 / √(the blurred amplitude), as the phase noise of a shot-noise
limited sensor does (σ_φ ∝ σ_I / B, σ_I ∝ √I, B ∝ I).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SutureCondition:
    """One suture condition.

    Attributes:
        diameter_mm: thread diameter = the crest's height over the tissue under it, mm.
        px_mm: pixel pitch on the tissue, mm.
        blur_px: Gaussian σ of the camera's blur (defocus, optics), px.
        noise_mm: depth noise σ on the tissue (albedo 1), mm; elsewhere it scales as 1/√albedo.
        polarity: ``"dark"`` or ``"bright"`` thread against the tissue.
        albedo: the thread's albedo relative to the tissue's (dark < 1 < bright).
        angle_deg: the thread's direction in the image, degrees from the +u axis.
        curvature_per_mm: (κ₁, κ₂) tissue curvatures along its principal axes, 1/mm (±).
        curvature_axis_deg: direction of the first principal axis, degrees.
        slope: (∂z/∂x, ∂z/∂y) tissue tilt, mm/mm.
    """

    diameter_mm: float
    px_mm: float
    blur_px: float
    noise_mm: float
    polarity: str
    albedo: float
    angle_deg: float
    curvature_per_mm: tuple[float, float]
    curvature_axis_deg: float
    slope: tuple[float, float]


def random_conditions(n: int, seed: int) -> list[SutureCondition]:
    """``n`` seeded random conditions, polarity alternating dark / bright.

    Ranges: diameter 0.3–0.9 mm; pitch 0.03–0.05 mm/px; blur σ 0–1.5 px; noise 0–0.04 mm;
    dark albedo 0.15–0.4, bright 1.8–3; any direction; curvatures ±(0–0.15)/mm (radii ≥ 6.7 mm);
    slopes ±0.3.
    """
    if n < 1:
        raise ValueError(f"n: need at least 1 condition, got {n}")
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        dark = i % 2 == 0
        out.append(SutureCondition(
            diameter_mm=float(rng.uniform(0.3, 0.9)), px_mm=float(rng.uniform(0.03, 0.05)),
            blur_px=float(rng.uniform(0.0, 1.5)), noise_mm=float(rng.uniform(0.0, 0.04)),
            polarity="dark" if dark else "bright",
            albedo=float(rng.uniform(0.15, 0.4) if dark else rng.uniform(1.8, 3.0)),
            angle_deg=float(rng.uniform(0.0, 180.0)),
            curvature_per_mm=(float(rng.uniform(-0.15, 0.15)), float(rng.uniform(-0.15, 0.15))),
            curvature_axis_deg=float(rng.uniform(0.0, 180.0)),
            slope=(float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-0.3, 0.3)))))
    return out


def suture_maps(cond: SutureCondition, seed: int, shape: tuple[int, int] = (200, 260)
                ) -> tuple[F64, F64, F64]:
    """Height map as reconstructed, texture and the true height map of one condition.

    Args:
        cond: the condition.
        seed: the noise's seed.
        shape: (H, W) pixels; the thread crosses the centre, 6 mm long (or the image's span).

    Returns:
        (depth (H, W) mm with blur and noise, texture (H, W) the blurred albedo (tissue 100),
        truth (H, W) mm, tissue plus thread without blur or noise). The thread's true height
        over the tissue is ``cond.diameter_mm``.
    """
    if cond.polarity not in ("dark", "bright"):
        raise ValueError(f"cond: polarity must be 'dark' or 'bright', got {cond.polarity!r}")
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (xx - (w - 1) / 2) * cond.px_mm, (yy - (h - 1) / 2) * cond.px_mm
    b = math.radians(cond.curvature_axis_deg)
    p, q = x * math.cos(b) + y * math.sin(b), -x * math.sin(b) + y * math.cos(b)
    k1, k2 = cond.curvature_per_mm
    tissue = 5.0 + cond.slope[0] * x + cond.slope[1] * y + 0.5 * (k1 * p * p + k2 * q * q)
    a = math.radians(cond.angle_deg)
    t = -x * math.sin(a) + y * math.cos(a)  # across the thread
    s = x * math.cos(a) + y * math.sin(a)  # along it
    r = cond.diameter_mm / 2
    half_len = min(3.0, 0.4 * min(h, w) * cond.px_mm)
    on = (np.abs(t) < r) & (np.abs(s) < half_len)
    truth = tissue + np.where(on, r + np.sqrt(np.clip(r * r - t * t, 0.0, None)), 0.0)
    albedo = np.where(on, cond.albedo, 1.0)
    if cond.blur_px > 0:
        amp = gaussian_filter(albedo, cond.blur_px, mode="nearest")
        depth = gaussian_filter(albedo * truth, cond.blur_px, mode="nearest") / amp
    else:
        amp, depth = albedo, truth.copy()
    rng = np.random.default_rng(seed)
    depth = depth + rng.normal(0.0, 1.0, shape) * cond.noise_mm / np.sqrt(amp)
    texture = 100.0 * amp + rng.normal(0.0, 1.0, shape)
    return depth, texture, truth


__all__ = ["SutureCondition", "random_conditions", "suture_maps"]
