"""VDI/VDE 2634-2 sphere figures: probing error form (PF) and size (PS).

PF is the range of the radial distances of the measured points to a least-squares
sphere with free radius; PS is the fitted diameter minus the calibrated diameter.
The guideline allows up to 0.3 % of the points to be excluded (``exclude_fraction``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.analysis.common import select_points

F64 = npt.NDArray[np.float64]


@dataclass
class SphereFit:
    """Least-squares sphere: centre (3,) mm, radius mm, radial residuals (n,) mm (|X−c| − r)."""

    center: F64
    radius_mm: float
    residuals_mm: F64


@dataclass
class SphereFigures:
    """PF, PS and the fit behind them.

    Attributes:
        diameter_mm: fitted diameter, mm.
        pf_mm: probing error form — range of radial residuals after exclusion, mm.
        ps_mm: probing error size — fitted minus calibrated diameter, mm.
        rms_mm: RMS radial residual, mm.
        n_points: points in the fit (after segmentation); inlier mask over the input
            points that passed validity/ROI is ``inliers``.
    """

    diameter_mm: float
    pf_mm: float
    ps_mm: float
    rms_mm: float
    n_points: int
    fit: SphereFit
    inliers: npt.NDArray[np.bool_]


def fit_sphere(points: npt.ArrayLike) -> SphereFit:
    """Geometric least-squares sphere through (n ≥ 4, 3) points (mm): algebraic start, then LM."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 4:
        raise ValueError(f"points: expected (n >= 4, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points: contains NaN or infinity")
    center, radius = _algebraic_sphere(pts)
    mean = pts.mean(axis=0)  # centre the problem for conditioning

    def resid(p: F64) -> F64:
        r: F64 = np.linalg.norm(pts - mean - p[:3], axis=1) - p[3]
        return r

    def jac(p: F64) -> F64:
        d = pts - mean - p[:3]
        r = np.linalg.norm(d, axis=1)[:, None]
        return np.concatenate([-d / r, -np.ones((len(pts), 1))], axis=1)

    from scipy.optimize import least_squares  # deferred: costs the live start-up CPU

    res = least_squares(resid, np.r_[center - mean, radius], jac=jac, method="lm")
    c = res.x[:3] + mean
    r = abs(float(res.x[3]))
    return SphereFit(c, r, np.linalg.norm(pts - c, axis=1) - r)


def _algebraic_sphere(pts: F64) -> tuple[F64, float]:
    mean = pts.mean(axis=0)
    q = pts - mean
    a = np.concatenate([2 * q, np.ones((len(q), 1))], axis=1)
    b = np.sum(q**2, axis=1)
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 4:
        raise ValueError("points: do not determine a sphere (coplanar or degenerate)")
    c = sol[:3]
    r2 = float(sol[3] + c @ c)
    if not r2 > 0:
        raise ValueError("points: do not determine a sphere (coplanar or degenerate)")
    return c + mean, math.sqrt(r2)


def sphere_figures(points: npt.ArrayLike, diameter_mm: float, valid: npt.ArrayLike | None = None, *,
                   roi: tuple[int, int, int, int] | None = None, exclude_fraction: float = 0.003,
                   segment: bool = True, band_mm: float | None = None,
                   seed: int = 0) -> SphereFigures:
    """PF and PS of a measured sphere of calibrated ``diameter_mm``.

    Args:
        points: (H, W, 3) point map or (n, 3) points, camera frame, mm; NaN invalid.
        diameter_mm: calibrated sphere diameter, mm.
        valid, roi: optional mask and pixel box (x0, y0, x1, y1) selecting the data.
        exclude_fraction: share of points with the largest |residual| left out of PF.
        segment: find the sphere among other surfaces first (RANSAC with radii within
            ±10 % of the nominal), then fit only its points.
        band_mm: RANSAC inlier band, mm; default min(0.1 mm, 2 % of the diameter) — narrow
            enough that the rim where a sphere meets its support does not outscore the sphere.
        seed: RANSAC seed.
    """
    if not (math.isfinite(diameter_mm) and diameter_mm > 0):
        raise ValueError(f"diameter_mm: must be positive, got {diameter_mm}")
    if not 0.0 <= exclude_fraction < 0.5:
        raise ValueError(f"exclude_fraction: must be in [0, 0.5), got {exclude_fraction}")
    pts = select_points(points, valid, roi)
    if len(pts) < 10:
        raise ValueError(f"points: need at least 10 valid points, got {len(pts)}")
    inliers = np.ones(len(pts), bool)
    if segment:
        inliers = _ransac_sphere(pts, diameter_mm / 2, band_mm or min(0.1, 0.02 * diameter_mm),
                                 seed)
    fit = fit_sphere(pts[inliers])
    if segment:  # refit once with the points near the least-squares sphere
        d = np.abs(np.linalg.norm(pts - fit.center, axis=1) - fit.radius_mm)
        sigma = 1.4826 * float(np.median(np.abs(fit.residuals_mm)))
        inliers = d <= max(4.0 * sigma, 1e-3)
        fit = fit_sphere(pts[inliers])
    r = fit.residuals_mm
    n = len(r)
    keep = np.sort(np.abs(r))[max(0, n - 1 - int(math.floor(exclude_fraction * n)))]
    kept = r[np.abs(r) <= keep]
    return SphereFigures(
        diameter_mm=2 * fit.radius_mm,
        pf_mm=float(kept.max() - kept.min()),
        ps_mm=2 * fit.radius_mm - diameter_mm,
        rms_mm=float(np.sqrt(np.mean(r**2))),
        n_points=n,
        fit=fit,
        inliers=inliers,
    )


def _ransac_sphere(pts: F64, radius_mm: float, band_mm: float, seed: int,
                   iterations: int = 400, score_size: int = 20000) -> npt.NDArray[np.bool_]:
    """Inliers of the best sphere with radius within ±10 % of ``radius_mm``.

    Samples are local (a random seed point and three points within one diameter of it),
    so a sphere covering a few per cent of the view is still hit; hypotheses are scored
    on a random subset.
    """
    rng = np.random.default_rng(seed)
    score = pts if len(pts) <= score_size else pts[rng.choice(len(pts), score_size, replace=False)]
    from scipy.spatial import cKDTree  # deferred, as least_squares

    tree = cKDTree(score)
    best_count, best = 0, None
    for _ in range(iterations):
        i = int(rng.integers(len(score)))
        near = tree.query_ball_point(score[i], 2.0 * radius_mm)
        if len(near) < 4:
            continue
        sample = score[rng.choice(near, 4, replace=False)]
        try:
            c, r = _algebraic_sphere(sample)
        except ValueError:
            continue
        if not (0.9 * radius_mm <= r <= 1.1 * radius_mm):
            continue
        count = int(np.sum(np.abs(np.linalg.norm(score - c, axis=1) - r) <= band_mm))
        if count > best_count:
            best_count, best = count, (c, r)
    if best is None:
        raise ValueError(f"points: no sphere of diameter ≈ {2 * radius_mm:g} mm found")
    c, r = best
    inl: npt.NDArray[np.bool_] = np.abs(np.linalg.norm(pts - c, axis=1) - r) <= band_mm
    if inl.sum() < 10:
        raise ValueError(f"points: no sphere of diameter ≈ {2 * radius_mm:g} mm found")
    return inl
