"""Plane accuracy and precision the way Le et al. (2018) measured their 45° target.

A plane is found by maximum-likelihood sample consensus (MLESAC, Torr & Zisserman
2000): random 3-point planes whose normal lies within 3° of the principal (PCA)
normal are scored by the likelihood of a Gaussian-inlier (σ from the 5 µm inlier
band) / uniform-outlier mixture; the best one is refined by least squares on its
consensus set. Signed distances to it are binned along the incline (bin width =
range / √N): per bin, accuracy = mean distance, precision = standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.analysis.common import select_points

F64 = npt.NDArray[np.float64]


@dataclass
class PlaneFit:
    """Plane ``normal · X + offset_mm = 0`` (unit normal), and its consensus set (n,) bool."""

    normal: F64
    offset_mm: float
    inliers: npt.NDArray[np.bool_]

    def distances_mm(self, points: npt.ArrayLike) -> F64:
        """Signed distances (mm) of (n, 3) points to the plane."""
        return np.asarray(points, np.float64) @ self.normal + self.offset_mm


@dataclass
class PlaneBin:
    """One bin along the incline: centre position (mm), count, mean and std distance (mm)."""

    center_mm: float
    count: int
    accuracy_mm: float
    precision_mm: float


@dataclass
class PlaneAccuracy:
    """Figures of a plane measurement.

    Attributes:
        accuracy_mm: count-weighted mean of the per-bin |mean distance|, mm (systematic error).
        precision_mm: pooled within-bin standard deviation of the distances, mm (random error).
        mean_distance_mm / std_distance_mm: over all points, mm.
        flatness_mm: VDI/VDE 2634-2 flatness error F: range of the distances to the plane
            after excluding ``exclude_fraction`` of the points with the largest |distance|.
        n_points: points analysed; inlier_fraction: share within the 5 µm band of the fit.
        plane: the fitted plane; bins: per-bin figures along the incline.
    """

    accuracy_mm: float
    precision_mm: float
    mean_distance_mm: float
    std_distance_mm: float
    flatness_mm: float
    n_points: int
    inlier_fraction: float
    plane: PlaneFit
    bins: list[PlaneBin] = field(default_factory=list)


def fit_plane_lsq(points: npt.ArrayLike) -> tuple[F64, float]:
    """Total least-squares plane of (n, 3) points: (unit normal, offset mm),
    normal·X + offset = 0."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 3:
        raise ValueError(f"points: expected (n >= 3, 3), got {pts.shape}")
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    normal = vt[2]
    return normal, float(-normal @ centroid)


def fit_plane_mlesac(points: npt.ArrayLike, *, inlier_mm: float = 0.005, max_angle_deg: float = 3.0,
                     iterations: int = 500, sample_size: int = 5000, seed: int = 0) -> PlaneFit:
    """MLESAC plane of (n, 3) points (mm).

    Args:
        points: (n, 3) float, mm, finite.
        inlier_mm: half-width of the inlier band, mm; inlier σ = inlier_mm / 1.96.
        max_angle_deg: hypotheses whose normal is further than this from the PCA normal
            are rejected.
        iterations: random 3-point hypotheses drawn.
        sample_size: points used to score hypotheses (a random subset, for speed).
        seed: random generator seed (results are reproducible).

    Returns:
        The :class:`PlaneFit`, refined by least squares on the consensus set.
    """
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 3:
        raise ValueError(f"points: expected (n >= 3, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points: contains NaN or infinity")
    if not inlier_mm > 0:
        raise ValueError(f"inlier_mm: must be positive, got {inlier_mm}")
    if iterations < 1:
        raise ValueError(f"iterations: must be >= 1, got {iterations}")
    rng = np.random.default_rng(seed)
    pca_normal, _ = fit_plane_lsq(pts)
    score_pts = (pts if len(pts) <= sample_size
                 else pts[rng.choice(len(pts), sample_size, replace=False)])
    sigma = inlier_mm / 1.96
    cos_max = math.cos(math.radians(max_angle_deg))
    idx = rng.integers(0, len(pts), size=(iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    normals = normals[ok] / norms[ok, None]
    a = a[ok]
    ok = np.abs(normals @ pca_normal) >= cos_max
    normals, a = normals[ok], a[ok]
    if len(normals) == 0:  # no admissible sample (tiny or degenerate data): fall back to PCA
        normal, offset = pca_normal, float(-pca_normal @ pts.mean(axis=0))
    else:
        offsets = -np.sum(normals * a, axis=1)
        costs = np.concatenate([
            _mlesac_cost(score_pts @ normals[i : i + 64].T + offsets[i : i + 64], sigma)
            for i in range(0, len(normals), 64)
        ])
        best = int(np.argmin(costs))
        normal, offset = normals[best], float(offsets[best])
    # Local optimisation: least squares on the consensus set, which then follows the fit.
    for _ in range(5):
        e = pts @ normal + offset
        spread = 1.4826 * float(np.median(np.abs(e)))
        band = max(inlier_mm, 2.5 * spread)
        sel = np.abs(e) <= band
        if sel.sum() < 3:
            break
        new_normal, new_offset = fit_plane_lsq(pts[sel])
        if new_normal @ normal < 0:
            new_normal, new_offset = -new_normal, -new_offset
        normal, offset = new_normal, new_offset
    inliers = np.abs(pts @ normal + offset) <= inlier_mm
    return PlaneFit(np.asarray(normal, np.float64), float(offset), inliers)


def _mlesac_cost(e: F64, sigma: float) -> F64:
    """Negative log-likelihood per hypothesis (columns of (m, k) residuals e),
    Gaussian/uniform mixture, γ by EM."""
    nu = np.maximum(np.ptp(e, axis=0), 6 * sigma)
    p_in = np.exp(-0.5 * (e / sigma) ** 2) / (math.sqrt(2 * math.pi) * sigma)
    p_out = 1.0 / nu
    gamma = np.full(e.shape[1], 0.5)
    for _ in range(3):
        g_in = gamma * p_in
        gamma = np.mean(g_in / (g_in + (1 - gamma) * p_out), axis=0)
    cost: F64 = -np.sum(np.log(gamma * p_in + (1 - gamma) * p_out), axis=0)
    return cost


def plane_accuracy(points: npt.ArrayLike, valid: npt.ArrayLike | None = None, *,
                   roi: tuple[int, int, int, int] | None = None, inlier_mm: float = 0.005,
                   max_angle_deg: float = 3.0, exclude_fraction: float = 0.003,
                   seed: int = 0) -> PlaneAccuracy:
    """Accuracy, precision and flatness of a measured plane (paper's method + VDI/VDE 2634-2 F).

    Args:
        points: (H, W, 3) point map or (n, 3) points, camera frame, mm; NaN = invalid.
        valid: optional (H, W) or (n,) bool mask, combined with finiteness.
        roi: (x0, y0, x1, y1) pixel box (x1, y1 exclusive), only for point maps.
        inlier_mm: MLESAC inlier band, mm (paper: 5 µm).
        max_angle_deg: allowed angle between hypothesis and PCA normals (paper: 3°).
        exclude_fraction: share of points with the largest |distance| left out of F.
        seed: MLESAC random seed.

    Bins run along the incline: the direction in the plane along which the camera's
    optical axis (z) rises fastest, or the main in-plane axis if the plane faces the camera.
    """
    pts = select_points(points, valid, roi)
    if len(pts) < 10:
        raise ValueError(f"points: need at least 10 valid points in the ROI, got {len(pts)}")
    if not 0.0 <= exclude_fraction < 0.5:
        raise ValueError(f"exclude_fraction: must be in [0, 0.5), got {exclude_fraction}")
    fit = fit_plane_mlesac(pts, inlier_mm=inlier_mm, max_angle_deg=max_angle_deg, seed=seed)
    dist = fit.distances_mm(pts)
    s = pts @ _incline_direction(pts, fit.normal)
    n = len(pts)
    n_bins = max(1, math.ceil(math.sqrt(n)))
    lo, hi = float(s.min()), float(s.max())
    width = (hi - lo) / n_bins if hi > lo else 1.0
    which = np.clip(((s - lo) / width).astype(np.int64), 0, n_bins - 1)
    counts = np.bincount(which, minlength=n_bins)
    sums = np.bincount(which, weights=dist, minlength=n_bins)
    sq = np.bincount(which, weights=dist**2, minlength=n_bins)
    bins: list[PlaneBin] = []
    acc_num = 0.0
    pooled_ss = 0.0
    pooled_dof = 0
    for b in np.nonzero(counts)[0]:
        c = int(counts[b])
        mean = sums[b] / c
        var = max(0.0, sq[b] / c - mean**2) * (c / (c - 1) if c > 1 else 0.0)
        bins.append(PlaneBin(lo + (b + 0.5) * width, c, float(mean), math.sqrt(var)))
        acc_num += c * abs(mean)
        if c > 1:
            pooled_ss += var * (c - 1)
            pooled_dof += c - 1
    keep = np.sort(np.abs(dist))[: max(1, n - int(math.floor(exclude_fraction * n)))][-1]
    kept = dist[np.abs(dist) <= keep]
    return PlaneAccuracy(
        accuracy_mm=acc_num / n,
        precision_mm=math.sqrt(pooled_ss / pooled_dof) if pooled_dof else math.nan,
        mean_distance_mm=float(dist.mean()),
        std_distance_mm=float(dist.std(ddof=1)),
        flatness_mm=float(kept.max() - kept.min()),
        n_points=n,
        inlier_fraction=float(fit.inliers.mean()),
        plane=fit,
        bins=bins,
    )


def _incline_direction(pts: F64, normal: F64) -> F64:
    z = np.array([0.0, 0.0, 1.0])
    g = z - (z @ normal) * normal
    if np.linalg.norm(g) > 0.05:  # more than ~3° of tilt toward the camera
        return g / np.linalg.norm(g)
    _, _, vt = np.linalg.svd(pts - pts.mean(axis=0), full_matrices=False)
    first: F64 = vt[0]
    return first
