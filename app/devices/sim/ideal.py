"""The exact Eq. (5) coefficients of the simulated pinhole rig — a test oracle.

For an undistorted pinhole camera, pixel (u, v) has ray r = ((u−cx)/fx, (v−cy)/fy, 1), so
X = t·r. The projector column of X is x_p = (α·X − α·C)/(γ·X − γ·C) (see
:meth:`ProjectorModel.column_coefficients`). Solving for t and taking the height
h = t·n·r + offset gives

    h = [(x_p γ·C − α·C)(n·r) + offset (x_p γ·r − α·r)] / (x_p γ·r − α·r),

whose numerator and denominator are both bilinear in x_p and affine in (u, v): exactly
Eq. (5) with the quadratic terms (c6..c11, d6..d11) zero. φ = 2π k_max x_p / w is linear
in x_p, and the normalisation (u', v', φ') is affine, so the form is preserved exactly.
The product never uses this: it calibrates from boards like the real instrument.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from app.core.schedule import PatternSchedule

if TYPE_CHECKING:
    from app.core.calibration import Calibration
    from app.devices.sim.optics import SimRig


def _bilinear_basis(phi: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    one = np.ones_like(phi)
    return np.stack([one, phi, u, phi * u, v, phi * v], -1)


def ideal_calibration(rig: SimRig, schedule: PatternSchedule | None = None,
                      height_range_mm: tuple[float, float] = (0.0, 22.0)) -> Calibration:
    """Calibration whose Eq. (5) reproduces the true height from the true finest phase.

    Exact when the camera has no distortion (``rig.dist`` all zero); the stored
    ``dist_coeffs`` are the rig's. Normalisation: u' = (u − W/2)/(W/2), v' likewise,
    φ' centred on the phase range of the calibrated heights at the image centre.
    """
    from app.core.calibration import Calibration

    schedule = schedule or PatternSchedule()
    cam, proj, plane = rig.camera, rig.projector, rig.reference
    K = cam.K
    w, h = cam.image_size
    k_max = schedule.frequencies[-1]
    # Phase per projector pixel along the fringe axis (columns for vertical fringes), radians.
    phi_per_col = 2.0 * math.pi * k_max / schedule.axis_length
    alpha, aC, gamma, gC = proj.fringe_coefficients(schedule.orientation)
    n, off = plane.normal, plane.offset_mm

    # Normalisation from the image centre and the calibrated height range.
    centre_ray = cam.rays(np.array([w / 2.0]), np.array([h / 2.0]))[0]
    phis = []
    for hh in height_range_mm:
        t = (hh - off) / (n @ centre_ray)
        phis.append(phi_per_col * float(proj.fringe_coordinate(t * centre_ray,
                                                               schedule.orientation)))
    phi0, sphi = 0.5 * (phis[0] + phis[1]), 0.5 * abs(phis[1] - phis[0])
    norm = {"u": (w / 2.0, w / 2.0), "v": (h / 2.0, h / 2.0), "phi": (phi0, sphi)}

    # Sample N and D at generic points in normalised coordinates and solve for the basis
    # coefficients (exact: both are in the span of the 6 bilinear monomials).
    rng = np.random.default_rng(0)
    up, vp, pp = (rng.uniform(-1.5, 1.5, 64) for _ in range(3))
    u, v = norm["u"][0] + norm["u"][1] * up, norm["v"][0] + norm["v"][1] * vp
    xp = (phi0 + sphi * pp) / phi_per_col
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    nr, gr, ar = r @ n, r @ gamma, r @ alpha
    den = xp * gr - ar
    num = (xp * gC - aC) * nr + off * den
    basis = _bilinear_basis(pp, up, vp)
    cn = np.linalg.lstsq(basis, num, rcond=None)[0]
    cd = np.linalg.lstsq(basis, den, rcond=None)[0]
    scale = cn[0]
    numerator = np.zeros(11)
    denominator = np.zeros(12)
    numerator[:5] = cn[1:] / scale  # c1..c5: φ, u, φu, v, φv
    denominator[:6] = cd / scale  # d0..d5
    return Calibration(
        camera_matrix=K.copy(), dist_coeffs=cam.dist.copy(), image_size=(w, h),
        plane_normal=n.copy(), plane_offset_mm=float(off), numerator=numerator,
        denominator=denominator, normalization=norm, pattern=schedule,
        height_range_mm=height_range_mm,
        extra={"source": "fringescope simulator ideal_calibration (oracle)"},
    )


def eq5_height(cal: Calibration, phi: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Evaluate Eq. (5) of ``cal`` (float64) — a reference evaluator for the simulator's tests."""
    norm = cal.normalization
    (u0, su), (v0, sv), (p0, sp) = norm["u"], norm["v"], norm["phi"]
    up, vp, pp = (u - u0) / su, (v - v0) / sv, (phi - p0) / sp
    c, d = cal.numerator, cal.denominator
    mon = [up, vp, up * up, vp * vp, up * vp]
    num = 1.0 + c[0] * pp
    den = d[0] + d[1] * pp
    for i, m in enumerate(mon):
        num = num + (c[1 + 2 * i] + c[2 + 2 * i] * pp) * m
        den = den + (d[2 + 2 * i] + d[3 + 2 * i] * pp) * m
    z: np.ndarray = num / den
    return z


def true_geometric_calibration(rig: SimRig, schedule: PatternSchedule | None = None,
                               height_range_mm: tuple[float, float] = (-8.0, 24.0)) -> Calibration:
    """The twin's own geometry as a calibration (a test oracle): the rig's camera (with its lens
    distortion), reference plane and projector pose and intrinsics along the fringe axis, in the
    geometric depth model (exact for a pinhole projector, any camera distortion), supported
    everywhere. Reconstructing with it separates what the rendering and reconstruction do from
    what a calibration fit adds.

    Raises:
        ValueError: horizontal fringes (not modelled here), naming ``schedule``.
    """
    from scipy.spatial.transform import Rotation

    from app.core.calibration import Calibration
    from app.core.depth_model import SupportedRegion
    from app.core.geometric import GeometricModel

    schedule = schedule or PatternSchedule()
    if schedule.orientation != "vertical":
        raise ValueError("schedule: the oracle models vertical fringes only")
    proj = rig.projector
    rot = proj.R.T  # camera → projector frame: X_p = Rᵀ (X − C)
    model = GeometricModel(Rotation.from_matrix(rot).as_rotvec(), -rot @ proj.centre,
                           float(proj.K[0, 0]), float(proj.K[0, 2]), 0.0, int(schedule.axis_length),
                           int(schedule.frequencies[-1]), region=SupportedRegion())
    return Calibration(rig.K.copy(), rig.dist.copy(), rig.image_size, rig.reference.normal.copy(),
                       float(rig.reference.offset_mm), pattern=schedule,
                       height_range_mm=height_range_mm, model=model,
                       extra={"source": "fringescope simulator true_geometric_calibration"})
