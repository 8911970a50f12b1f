"""Board poses refined by the fringe phase: a joint fit of every board's pose and the projector.

A bench board that covers only the centre of the field is small against its distance, so
its tilt from the corners alone (perspective-n-point) is poorly determined: 0.05 px of corner
noise tilts an 8 mm board seen from 40 mm by a milliradian or more. Pose 0's board *is* the
reference plane, so its tilt error becomes a height error growing across the field (±0.01 mm
over ±10 mm), and the other poses' errors bend the depth model.

The phase measured densely over each board constrains its plane far better: the projector's
surface of equal phase (:mod:`app.core.geometric`) must meet the camera ray of every board
pixel on the board. :func:`refine_board_poses` minimises, jointly over the projector (pose,
focal length, principal point and k1 along the fringe axis) and every board pose, the corner
reprojection errors and the projector-coordinate residuals of the board pixels, each divided
by its own noise scale (phase outliers beyond 5 scales dropped first), and over the camera
intrinsics (focal lengths, principal point and the distortion terms the camera calibration
chose): the corners of a small board leave the principal point loose by about a pixel, and the
board pixels' rays depend on it. The corners fix what the phase cannot (the board's position
within its plane, the overall scale); the phase fixes the tilts the corners leave loose.

The joint fit is kept only if it does not spoil the camera (:func:`check_refinement`): a
projector the model does not describe (lens distortion across the fringes, an uncorrected
gamma) drags the camera and poses to fit its phase, and the corners then show it. The corners'
noise comes from the corners-only fit: σ² = SSR₀ / (2n − p) px² per coordinate (SSR₀ its sum
of squared corner residuals over n corners, p its free parameters: intrinsics, the free
distortion terms, six per view). Moving those p parameters by Δθ raises the corners' sum of
squares by ΔSSR = Δθᵀ JᵀJ Δθ, so ΔSSR / σ² is the squared Mahalanobis distance of the joint
fit's camera and poses from the corners-only ones in the corners' own covariance σ²(JᵀJ)⁻¹.
The joint fit is accepted when ΔSSR / σ² ≤ χ²_p(0.99): its camera lies within the corners'
99 % confidence region; otherwise the corners-only camera and poses stand, with the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from app.core.geometric import _decompose, _dlt_1d, _rotation

F64 = npt.NDArray[np.float64]
ACCEPT_QUANTILE = 0.99  # the joint fit's camera must lie within the corners' 99 % confidence region
MIN_PHASE_POINTS = 50  # per pose
OUTLIER_SCALES = 5.0  # board pixels whose start residual exceeds 5 robust noise scales are dropped


@dataclass
class RefinedPoses:
    """Result of :func:`refine_board_poses`: the camera (``camera_matrix`` (3, 3), ``dist_coeffs``
    (5,)), per view ``rvecs``/``tvecs`` (3, 1), the corners' RMS reprojection error (px, per
    corner as ``cv2.calibrateCamera`` reports it: √(Σ|Δuv|² / n)) and the board normals' change
    (mrad) per view."""

    camera_matrix: F64
    dist_coeffs: F64
    rvecs: list[F64]
    tvecs: list[F64]
    reprojection_px: float
    tilt_change_mrad: list[float]


def _plane_points(rays: F64, rvec: F64, tvec: F64) -> F64:
    rot = _rotation(rvec)
    n = rot[:, 2]
    return np.asarray(rays * ((n @ tvec) / (rays @ n))[:, None], np.float64)


def undistort_rays(uv: F64, cam: F64, dist: F64, iterations: int = 20) -> F64:
    """(n, 3) undistorted rays (x, y, 1) of pixels ``uv`` (n, 2) under OpenCV's k1, k2, p1, p2, k3
    model (fixed-point iteration, as ``cv2.undistortPoints``; differentiable in the intrinsics)."""
    k1, k2, p1, p2, k3 = (list(np.ravel(dist)) + [0.0] * 5)[:5]
    xd = (uv[:, 0] - cam[0, 2]) / cam[0, 0]
    yd = (uv[:, 1] - cam[1, 2]) / cam[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        xn = (xd - dx) / radial
        yn = (yd - dy) / radial
        step = float(np.max(np.abs(xn - x) + np.abs(yn - y))) if x.size else 0.0
        x, y = xn, yn
        if step < 1e-13:
            break
    return np.stack([x, y, np.ones_like(x)], axis=1)


def refine_board_poses(
    obj: list[npt.NDArray[np.float32]],
    img: list[npt.NDArray[np.float32]],
    cam: F64,
    dist: F64,
    rvecs: list[F64],
    tvecs: list[F64],
    pixels: list[F64],
    proj_x: list[F64],
    weights: list[F64] | None = None,
    free_dist: tuple[int, ...] = (0,),
) -> RefinedPoses | None:
    """Jointly refine the camera, the board poses and the projector from corners and the phase
    on the boards.

    Args:
        obj, img: per view (n, 3) board points (mm) and (n, 1, 2) detected pixels.
        cam, dist: initial camera intrinsics (3, 3) and OpenCV distortion (k1, k2, p1, p2, k3).
        rvecs, tvecs: per view initial board pose (OpenCV convention).
        pixels: per view (m, 2) pixel coordinates (u, v) of board pixels.
        proj_x: per view (m,) projector coordinate along the fringe axis of those pixels
            (the finest unwrapped phase scaled to projector pixels), NaN where invalid.
        weights: optional per view (m,) relative precision of each pixel's phase (e.g. its
            modulation B over the view's median: σ_φ ∝ 1/B); None weighs them alike.
        free_dist: indices (into k1, k2, p1, p2, k3) of the distortion terms refined; the
            others stay as given.

    Returns:
        :class:`RefinedPoses`, or None when the data do not allow it (too few phase points,
        a degenerate projector start or a failed fit) — the corner calibration then stands.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    nv = len(obj)
    wts = weights if weights is not None else [np.ones(len(p)) for p in proj_x]
    keep = [np.isfinite(p) & np.isfinite(w) & (w > 0) for p, w in zip(proj_x, wts, strict=True)]
    if nv < 3 or any(int(k.sum()) < MIN_PHASE_POINTS for k in keep):
        return None
    pix = [np.asarray(q, np.float64)[k] for q, k in zip(pixels, keep, strict=True)]
    xps = [np.asarray(p, np.float64)[k] for p, k in zip(proj_x, keep, strict=True)]
    wts = [np.asarray(w, np.float64)[k] for w, k in zip(wts, keep, strict=True)]
    cam = np.asarray(cam, np.float64)
    dist5 = (list(np.ravel(np.asarray(dist, np.float64))) + [0.0] * 5)[:5]
    free = tuple(int(i) for i in free_dist)
    n_cam = 4 + len(free)
    cam0 = np.array([cam[0, 0], cam[1, 1], cam[0, 2], cam[1, 2]] + [dist5[i] for i in free])
    pose0 = np.concatenate(
        [np.concatenate([np.ravel(rv), np.ravel(tv)]) for rv, tv in zip(rvecs, tvecs, strict=True)]
    )
    obj64 = [np.asarray(o, np.float64) for o in obj]
    img64 = [np.asarray(i, np.float64).reshape(-1, 2) for i in img]
    o_cam, o_pose = 8, 8 + n_cam

    def camera(x: F64) -> tuple[F64, F64]:
        c = x[o_cam:o_pose]
        k = np.array([[c[0], 0.0, c[2]], [0.0, c[1], c[3]], [0.0, 0.0, 1.0]])
        d = np.array(dist5, np.float64)
        d[list(free)] = c[4:]
        return k, d

    def pose(x: F64, k: int) -> F64:
        return x[o_pose + 6 * k: o_pose + 6 * k + 6]

    def corner_res(x: F64, k: int, kd: tuple[F64, F64]) -> F64:
        q = pose(x, k)
        uv, _ = cv2.projectPoints(obj64[k], q[:3], q[3:], kd[0], kd[1])
        return np.asarray((uv.reshape(-1, 2) - img64[k]).ravel(), np.float64)

    def phase_res(x: F64, k: int, kd: tuple[F64, F64], rays: list[F64] | None = None) -> F64:
        """View k's phase residuals (m,), projector px × weight; ``rays``: the views' (m, 3)
        undistorted rays under ``kd`` when already known (they depend on the camera alone)."""
        q = pose(x, k)
        ray_k = undistort_rays(pix[k], kd[0], kd[1]) if rays is None else rays[k]
        pts = _plane_points(ray_k, q[:3], q[3:])
        r = _rotation(x[:3])
        xn = (pts @ r[0] + x[3]) / (pts @ r[2] + x[4])
        xd = (xps[k] - x[6]) / x[5]
        return np.asarray(wts[k] * x[5] * (xd * (1.0 + x[7] * xd * xd) - xn), np.float64)

    # projector start: 1-D DLT on the corner poses' board points, then its own fit
    x_init = np.concatenate([np.zeros(8), cam0, pose0])
    kd0 = camera(x_init)
    # the start's camera is fixed: its rays are undistorted once, not on every evaluation
    rays0 = [undistort_rays(pix[k], *kd0) for k in range(nv)]
    x3 = np.concatenate(
        [_plane_points(rays0[k], pose(x_init, k)[:3], pose(x_init, k)[3:]) for k in range(nv)]
    )
    try:
        rot, t, f, c = _decompose(_dlt_1d(x3, np.concatenate(xps)), x3)
    except (ValueError, np.linalg.LinAlgError):
        return None
    x_init[:8] = np.concatenate([Rotation.from_matrix(rot).as_rotvec(), [t[0], t[2], f, c, 0.0]])

    def proj_only(xp: F64) -> F64:
        xx = np.concatenate([xp, x_init[8:]])
        return np.concatenate([phase_res(xx, k, kd0, rays0) for k in range(nv)])

    try:
        start = least_squares(proj_only, x_init[:8], method="lm", x_scale="jac", max_nfev=2000)
    except (ValueError, np.linalg.LinAlgError):
        return None
    x_init[:8] = start.x
    # noise scales; phase outliers (order slips, board edges) beyond OUTLIER_SCALES dropped
    s_corner = max(
        float(
            np.sqrt(np.mean(np.concatenate([corner_res(x_init, k, kd0) for k in range(nv)]) ** 2))
        ),
        1e-3,
    )
    s_phase = []
    for k in range(nv):
        r0 = phase_res(x_init, k, kd0, rays0)
        s = max(1.4826 * float(np.median(np.abs(r0))), 1e-4)
        ok = np.abs(r0) <= OUTLIER_SCALES * s
        if int(ok.sum()) < MIN_PHASE_POINTS:
            return None
        pix[k], xps[k], wts[k] = pix[k][ok], xps[k][ok], wts[k][ok]
        s_phase.append(s)

    n_c = [2 * len(o) for o in obj64]
    n_p = [len(p) for p in xps]
    c_start = np.concatenate([[0], np.cumsum(n_c)])
    p_start = c_start[-1] + np.concatenate([[0], np.cumsum(n_p)])
    support = [
        np.concatenate(
            [np.arange(c_start[k], c_start[k + 1]), np.arange(p_start[k], p_start[k + 1])]
        )
        for k in range(nv)
    ]

    def residuals(x: F64, rays: list[F64] | None = None) -> F64:
        kd = camera(x)
        parts = [corner_res(x, k, kd) / s_corner for k in range(nv)]
        parts += [phase_res(x, k, kd, rays) / s_phase[k] for k in range(nv)]
        return np.concatenate(parts)

    def jacobian(x: F64) -> F64:
        """Forward differences, the views' pose columns perturbed together (disjoint rows).

        The rays are undistorted once for ``x``'s camera and reused for the columns that leave
        the camera as it is (projector and poses): the iterative undistortion was most of the
        cost, repeated for each of those columns with the same result."""
        rays = [undistort_rays(pix[k], *camera(x)) for k in range(nv)]
        f0 = residuals(x, rays)
        jac = np.zeros((f0.size, x.size))
        for j in range(o_pose):  # projector and camera: every row
            h = 1e-7 * max(1.0, abs(float(x[j])))
            xx = x.copy()
            xx[j] += h
            jac[:, j] = (residuals(xx, rays if j < o_cam else None) - f0) / h
        for i in range(6):
            xx = x.copy()
            hs = [1e-7 * max(1.0, abs(float(x[o_pose + 6 * k + i]))) for k in range(nv)]
            for k in range(nv):
                xx[o_pose + 6 * k + i] += hs[k]
            d = residuals(xx, rays) - f0
            for k in range(nv):
                jac[support[k], o_pose + 6 * k + i] = d[support[k]] / hs[k]
        return jac

    try:
        res = least_squares(
            residuals, x_init, jac=jacobian, method="lm", x_scale="jac", max_nfev=100
        )
    except (ValueError, np.linalg.LinAlgError):
        return None
    x = res.x
    if not np.all(np.isfinite(x)) or x[o_cam] <= 0 or x[o_cam + 1] <= 0:
        return None
    kd = camera(x)
    out_r = [pose(x, k)[:3].reshape(3, 1).copy() for k in range(nv)]
    out_t = [pose(x, k)[3:].reshape(3, 1).copy() for k in range(nv)]
    # per corner (both coordinates), as cv2.calibrateCamera's RMS: comparable with the corner fit
    corner_all = np.concatenate([corner_res(x, k, kd) for k in range(nv)])
    reproj = float(np.sqrt(2.0 * np.mean(corner_all**2)))
    change = [
        1e3
        * math.acos(
            min(1.0, abs(float(_rotation(np.ravel(a))[:, 2] @ _rotation(np.ravel(b))[:, 2])))
        )
        for a, b in zip(rvecs, out_r, strict=True)
    ]
    return RefinedPoses(kd[0], kd[1], out_r, out_t, reproj, change)


@dataclass
class RefinementCheck:
    """Whether the joint (corners + phase) fit keeps the camera within the corners' noise.

    Attributes:
        accepted: True: the joint fit's camera and poses are used; False: the corners-only ones.
        corners_rms_px: the corners-only fit's RMS reprojection error, px per corner (OpenCV's).
        joint_rms_px: the joint fit's RMS reprojection error on the same corners, px per corner.
        noise_px: the corners' noise σ per coordinate, px: √(SSR₀ / (2n − p)).
        chi2: ΔSSR / σ², the joint fit's squared Mahalanobis distance from the corners-only fit.
        chi2_limit: χ²_p at :data:`ACCEPT_QUANTILE`, p = ``parameters``.
        parameters: free parameters of the corner fit (intrinsics, distortion terms, 6 per view).
        reason: one line saying what was kept and why.
    """

    accepted: bool
    corners_rms_px: float
    joint_rms_px: float
    noise_px: float
    chi2: float
    chi2_limit: float
    parameters: int
    reason: str

    def to_dict(self) -> dict[str, object]:
        """JSON-able record (calibration file, REST answer); non-finite numbers as None."""
        def num(x: float) -> float | None:
            return round(float(x), 6) if math.isfinite(x) else None

        return {"accepted": self.accepted, "corners_rms_px": num(self.corners_rms_px),
                "joint_rms_px": num(self.joint_rms_px), "noise_px": num(self.noise_px),
                "chi2": num(self.chi2), "chi2_limit": num(self.chi2_limit),
                "parameters": self.parameters, "reason": self.reason}


def corner_sum_squares(obj: list[npt.NDArray[np.float32]], img: list[npt.NDArray[np.float32]],
                       cam: F64, dist: F64, rvecs: list[F64], tvecs: list[F64]
                       ) -> tuple[float, int]:
    """Sum of squared corner reprojection residuals (px², both coordinates) and the corner count.

    Args:
        obj, img: per view (n, 3) board points (mm) and (n, 1, 2) detected pixels.
        cam, dist: camera matrix (3, 3) and OpenCV distortion (k1, k2, p1, p2, k3).
        rvecs, tvecs: per view board pose (OpenCV convention).
    """
    ssr, n = 0.0, 0
    for o, i, rv, tv in zip(obj, img, rvecs, tvecs, strict=True):
        uv, _ = cv2.projectPoints(np.asarray(o, np.float64), rv, tv, cam, dist)
        d = uv.reshape(-1, 2) - np.asarray(i, np.float64).reshape(-1, 2)
        ssr += float(np.sum(d * d))
        n += len(d)
    return ssr, n


def check_refinement(obj: list[npt.NDArray[np.float32]], img: list[npt.NDArray[np.float32]],
                     cam: F64, dist: F64, rvecs: list[F64], tvecs: list[F64],
                     refined: RefinedPoses, free_dist: tuple[int, ...]) -> RefinementCheck:
    """Accept the joint fit only if its corners stay within their noise of the corners-only fit.

    Args:
        obj, img: per view (n, 3) board points (mm) and (n, 1, 2) detected pixels.
        cam, dist, rvecs, tvecs: the corners-only calibration (least squares on the corners).
        refined: the joint fit (:func:`refine_board_poses`).
        free_dist: the distortion terms both fits leave free (indices into k1, k2, p1, p2, k3).

    Returns:
        :class:`RefinementCheck` (the rule is in the module docstring).
    """
    from scipy.stats import chi2 as chi2_dist

    ssr0, n = corner_sum_squares(obj, img, cam, dist, rvecs, tvecs)
    ssr1, _ = corner_sum_squares(obj, img, refined.camera_matrix, refined.dist_coeffs,
                                 refined.rvecs, refined.tvecs)
    p = 4 + len(free_dist) + 6 * len(obj)
    dof = 2 * n - p
    if dof <= 0:
        raise ValueError(f"obj: {n} corners cannot determine {p} camera and pose parameters")
    noise2 = max(ssr0 / dof, 1e-12)
    chi2 = max(ssr1 - ssr0, 0.0) / noise2
    limit = float(chi2_dist.ppf(ACCEPT_QUANTILE, p))
    rms0, rms1 = math.sqrt(ssr0 / n), math.sqrt(ssr1 / n)
    accepted = bool(math.isfinite(ssr1) and chi2 <= limit)
    what = (f"corner reprojection {rms1:.3f} px (corners only {rms0:.3f} px, noise "
            f"{math.sqrt(noise2):.3f} px per coordinate): chi2 {chi2:.1f} "
            f"{'<=' if accepted else '>'} {limit:.1f} (p = {p}, {100 * ACCEPT_QUANTILE:.0f} %)")
    reason = (f"phase refinement accepted: {what}" if accepted else
              f"phase refinement rejected, the corners-only camera and poses are kept: the phase "
              f"drags the camera beyond the corners' noise ({what}); the projector does not follow "
              f"the model (lens distortion across the fringes, uncorrected gamma?)")
    return RefinementCheck(accepted, rms0, rms1, math.sqrt(noise2), chi2, limit, p, reason)
