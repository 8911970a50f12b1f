"""Validation analytics: plane accuracy/precision, feature height, VDI/VDE 2634-2 figures."""

from app.analysis.common import parse_roi, roi_mask, select_points
from app.analysis.feature import FeatureHeight, feature_height
from app.analysis.groundtruth import DepthErrors, depth_errors, perpendicular_noise_mm
from app.analysis.noise import dz_dphi, height_noise_mm, phase_noise_rad
from app.analysis.plane import (
    PlaneAccuracy,
    PlaneBin,
    PlaneFit,
    fit_plane_lsq,
    fit_plane_mlesac,
    plane_accuracy,
)
from app.analysis.sphere import SphereFigures, SphereFit, fit_sphere, sphere_figures

__all__ = [
    "DepthErrors",
    "FeatureHeight",
    "PlaneAccuracy",
    "PlaneBin",
    "PlaneFit",
    "SphereFigures",
    "SphereFit",
    "depth_errors",
    "dz_dphi",
    "feature_height",
    "height_noise_mm",
    "phase_noise_rad",
    "fit_plane_lsq",
    "fit_plane_mlesac",
    "fit_sphere",
    "parse_roi",
    "perpendicular_noise_mm",
    "plane_accuracy",
    "roi_mask",
    "select_points",
    "sphere_figures",
]
