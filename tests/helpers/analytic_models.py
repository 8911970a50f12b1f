"""Depth models on the analytic rig (app.devices.sim.analytic_rig): the projector's forward
phase, board samples drawn through it, and geometric models fitted to them with a real
jackknife. Shared by the depth-model, σ_model and measurement tests."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from app.calib.model import undistort_points
from app.core.calibration import Calibration
from app.core.depth_model import BoardSamples, DepthModel, ReferencePlane
from app.core.geometric import GeometricModel
from app.devices.sim.analytic_rig import Rig


def geometric_of(rig: Rig, k1: float = 0.0) -> GeometricModel:
    """The rig's exact geometric model (projector distortion ``k1``)."""
    return rig.geometric_model(k1)


def rig_calibration(rig: Rig, model: DepthModel, dist: np.ndarray | None = None,
                    height_range_mm: tuple[float, float] = (0.0, 30.0)) -> Calibration:
    """A calibration of the rig's camera (``dist`` its distortion, none by default) holding
    ``model``."""
    return Calibration(rig.K, np.zeros(5) if dist is None else dist, (rig.width, rig.height),
                       rig.n, rig.plane_offset_mm, model=model, pattern=rig.schedule,
                       height_range_mm=height_range_mm)


def projector_phase(model: GeometricModel, x: np.ndarray) -> np.ndarray:
    """Forward model: camera-frame points (n, 3) mm → finest phase (n,) rad, through the
    projector's distortion: OpenCV's radial term, or for a ``k1_radial`` False model its inverse
    along x (solved here by root finding)."""
    r = model.rotation
    z = x @ r[2] + model.t_mm[2]
    xn = (x @ r[0] + model.t_mm[0]) / z
    if model.k1_radial:
        yn = (x @ r[1] + model.t_mm[1]) / z
        xd = xn * (1.0 + model.k1 * (xn * xn + yn * yn))
    else:
        xd = np.array([brentq(lambda d, target=t: d * (1 + model.k1 * d * d) - target, -1.0, 1.0)
                       for t in xn])
    xp = model.focal_px * xd + model.principal_px
    return 2 * math.pi * model.fringes * xp / model.projector_width_px


def board_samples(rig: Rig, model: GeometricModel, dist: np.ndarray, plane: ReferencePlane,
                  n: int = 3000, seed: int = 2) -> BoardSamples:
    """``n`` noise-free samples over the whole image at heights 0–30 mm, six poses."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, rig.width - 1, n), rng.uniform(0, rig.height - 1, n)
    z = rng.uniform(0.0, 30.0, n)
    rays = undistort_points(np.stack([u, v], 1), rig.K, dist)
    r3 = np.concatenate([rays, np.ones((n, 1))], axis=1)
    x = r3 * ((z - plane.offset_mm) / (r3 @ plane.normal))[:, None]
    phi = projector_phase(model, x)
    return BoardSamples(u, v, rays, phi, z, (np.arange(n) % 6).astype(np.int64),
                        (rig.width, rig.height), rig.schedule.frequencies[-1], rig.schedule.width)


def band_samples(rig: Rig, model: GeometricModel, plane: ReferencePlane,
                 z_mm: tuple[float, float], noise_rad: float, seed: int,
                 n: int = 3000) -> BoardSamples:
    """Samples over the whole image but only within the height band ``z_mm``, phase noise
    added."""
    s = board_samples(rig, model, np.zeros(5), plane, n=n, seed=seed)
    rng = np.random.default_rng(seed + 1000)
    z = rng.uniform(z_mm[0], z_mm[1], n)
    r3 = np.concatenate([s.ray_xy, np.ones((n, 1))], axis=1)
    x = r3 * ((z - plane.offset_mm) / (r3 @ plane.normal))[:, None]
    phi = projector_phase(model, x) + rng.normal(0.0, noise_rad, n)
    return BoardSamples(s.u, s.v, s.ray_xy, phi, z, s.pose, s.image_size, s.fringes,
                        s.projector_width_px)


def band_fitted_calibration(seed: int) -> tuple[Rig, Calibration]:
    """The default rig and a geometric model fitted to noisy board samples (0.05 rad) in the
    8–22 mm band: its jackknife over poses is real, valid columns ≳ 90 (the rest lies beyond
    the boards' phases)."""
    rig = Rig()
    plane = ReferencePlane(rig.n, rig.plane_offset_mm)
    model = GeometricModel.fit(
        band_samples(rig, geometric_of(rig), plane, (8.0, 22.0), 0.05, seed=seed), plane
    )
    return rig, rig_calibration(rig, model)
