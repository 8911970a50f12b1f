"""Eq. (5) of Le et al. (2018): the fit and evaluation live in :mod:`app.core.eq5`; this
module keeps the calibration-level reference evaluation of any depth model."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration

F64 = npt.NDArray[np.float64]

__all__ = ["height_mm", "undistort_points", "undistorted_rays"]


def undistort_points(
    uv: npt.ArrayLike, camera_matrix: npt.ArrayLike, dist_coeffs: npt.ArrayLike
) -> F64:
    """(n, 2) undistorted normalised rays (x, y) of pixel coordinates ``uv`` (n, 2), iterated to
    convergence (OpenCV's default 5 iterations leave ~1e-4 of error with strong distortion)."""
    pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
    dist = np.asarray(dist_coeffs, np.float64).ravel()
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    out = cv2.undistortPoints(
        pts,
        np.asarray(camera_matrix, np.float64),
        dist if dist.size else None,
        None,
        None,
        criteria=criteria,
    )
    return np.asarray(out, np.float64).reshape(-1, 2)


def undistorted_rays(calibration: Calibration, u: npt.ArrayLike, v: npt.ArrayLike) -> F64:
    """(n, 2) undistorted normalised camera rays (x, y) of pixels (u, v)."""
    uv = np.stack([np.asarray(u, np.float64).ravel(), np.asarray(v, np.float64).ravel()], axis=1)
    return undistort_points(uv, calibration.camera_matrix, calibration.dist_coeffs)


def height_mm(
    calibration: Calibration, u: npt.ArrayLike, v: npt.ArrayLike, phi: npt.ArrayLike
) -> F64:
    """Height above the reference plane (mm) at pixel (u, v) with finest-frequency phase φ (rad).

    A plain float64 reference implementation of the calibration's depth model (flat array).
    """
    uu = np.asarray(u, np.float64).ravel()
    vv = np.asarray(v, np.float64).ravel()
    pp = np.asarray(phi, np.float64).ravel()
    rays = (
        undistorted_rays(calibration, uu, vv)
        if calibration.model.name != "eq5"
        else np.zeros((uu.size, 2))
    )
    return calibration.model.height_at(uu, vv, rays, pp, calibration.reference_plane)
