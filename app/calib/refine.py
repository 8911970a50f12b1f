"""Board poses refined by the fringe phase: a joint fit of every board's pose and the projector.

A bench board that covers only the centre of the field is small against its distance, so
its tilt from the corners alone (perspective-n-point) is poorly determined: 0.05 px of corner
noise tilts an 8 mm board seen from 40 mm by a milliradian or more. Pose 0's board *is* the
reference plane, so its tilt error becomes a height error growing across the field (±0.01 mm
over ±10 mm), and the other poses' errors bend the depth model.

The phase measured densely over each board constrains its plane far better: the projector's
surface of equal phase (:mod:`app.core.geometric`) must meet the camera ray of every board
pixel on the board. :func:`refine_board_poses` minimises, jointly over the projector (pose,
focal length and principal point along the fringe axis, and its lens's radial k1 as the depth
model has it, t_y = 0) and every board pose, the corner
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
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from app.calib.levenberg import levenberg_marquardt
from app.core.geometric import _decompose, _dlt_1d, _rotation

F64 = npt.NDArray[np.float64]
ACCEPT_QUANTILE = 0.99  # the joint fit's camera must lie within the corners' 99 % confidence region
MIN_PHASE_POINTS = 50  # per pose
OUTLIER_SCALES = 5.0  # board pixels whose start residual exceeds 5 robust noise scales are dropped


@dataclass(frozen=True)
class NoiseScales:
    """The joint fit's weights: the corners' noise scale (px) and per view the phase's
    (projector px), each residual divided by its scale."""

    corner_px: float
    phase_px: tuple[float, ...]

    def of_views(self, views: list[int]) -> NoiseScales:
        """The scales of the views ``views`` (indices into :attr:`phase_px`), in that order."""
        return NoiseScales(self.corner_px, tuple(self.phase_px[k] for k in views))


@dataclass
class RefinedPoses:
    """Result of :func:`refine_board_poses`: the camera (``camera_matrix`` (3, 3), ``dist_coeffs``
    (5,)), per view ``rvecs``/``tvecs`` (3, 1), the corners' RMS reprojection error (px, per
    corner as ``cv2.calibrateCamera`` reports it: √(Σ|Δuv|² / n)) and the board normals' change
    (mrad) per view, and the projector of the joint fit (8,): rotation vector, t_x, t_z (mm),
    focal length and principal point (px), k1 — what a refit of a subset of the views may start
    from — and the noise scales it weighed the residuals by (:class:`NoiseScales`), which a refit
    of a subset keeps."""

    camera_matrix: F64
    dist_coeffs: F64
    rvecs: list[F64]
    tvecs: list[F64]
    reprojection_px: float
    tilt_change_mrad: list[float]
    projector: F64 | None = None
    noise_scales: NoiseScales | None = None


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


def undistort_rays_jacobian(rays: F64, cam: F64, dist: F64, free: tuple[int, ...]) -> F64:
    """(n, 2, 4 + len(free)) derivatives of the undistorted rays' (x, y) (:func:`undistort_rays`)
    with respect to the camera's fx, fy, cx, cy (px) and the distortion terms ``free`` (indices
    into k1, k2, p1, p2, k3), at fixed pixels.

    Implicit differentiation of the distortion equations ``D(x, y; k) = ((u − cx) / fx,
    (v − cy) / fy)`` the undistortion solves: d(x, y) = J_D⁻¹ (d rhs − ∂D/∂k dk), J_D the
    2 × 2 derivative of the distortion in (x, y) at the ray.

    Args:
        rays: (n, 3) float64 undistorted rays (x, y, 1) of the pixels under ``cam``, ``dist``.
        cam: (3, 3) camera matrix, px; dist: OpenCV (k1, k2, p1, p2, k3) (fewer: zeros).
        free: the distortion terms differentiated, in this order after the four intrinsics.
    """
    k1, k2, p1, p2, k3 = (list(np.ravel(dist)) + [0.0] * 5)[:5]
    fx, fy = float(cam[0, 0]), float(cam[1, 1])
    x, y = rays[:, 0], rays[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)  # d radial / d r²
    # J_D: the distortion's derivative in (x, y)
    a = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    c = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    det = a * d - b * c
    # the distorted normalised coordinates x_d = x·radial + dx, y_d = y·radial + dy
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    zero = np.zeros_like(x)
    # d(rhs)/dθ − ∂D/∂θ per parameter: (2, n) each
    rhs = [np.stack([-xd / fx, zero]), np.stack([zero, -yd / fy]),
           np.stack([np.full_like(x, -1.0 / fx), zero]),
           np.stack([zero, np.full_like(x, -1.0 / fy)])]
    d_dist = [np.stack([x * r2, y * r2]), np.stack([x * r2 * r2, y * r2 * r2]),
              np.stack([2.0 * x * y, r2 + 2.0 * y * y]),
              np.stack([r2 + 2.0 * x * x, 2.0 * x * y]), np.stack([x * r2**3, y * r2**3])]
    rhs += [-d_dist[i] for i in free]
    out = np.empty((len(x), 2, len(rhs)))
    for j, (gx, gy) in enumerate(rhs):
        out[:, 0, j] = (d * gx - b * gy) / det
        out[:, 1, j] = (a * gy - c * gx) / det
    return out


@dataclass
class JointProblem:
    """The joint fit's residuals and their exact Jacobian (:func:`refine_board_poses`).

    The state ``x`` (float64) is the projector (rotation vector (3), t_x, t_z mm, focal length
    and principal point px, the lens's radial k1), the camera (fx, fy, cx, cy px and the
    distortion terms ``free``) and per view its board pose (rotation vector, translation mm).
    The residuals are every view's corner reprojection errors (px, u and v interleaved) over
    ``s_corner``, then every view's phase residuals (projector px × weight) over its
    ``s_phase``.

    Attributes:
        obj: per view (n, 3) board points, mm; img: per view (n, 2) detected pixels.
        pix: per view (m, 2) board pixels; xps: (m,) their projector coordinates, px;
            wts: (m,) their phase weights.
        dist5: the distortion (k1, k2, p1, p2, k3) whose terms outside ``free`` stay fixed.
        free: the distortion terms in the state.
        s_corner: the corners' noise scale, px; s_phase: per view the phase's, projector px.
    """

    obj: list[F64]
    img: list[F64]
    pix: list[F64]
    xps: list[F64]
    wts: list[F64]
    dist5: list[float]
    free: tuple[int, ...]
    s_corner: float = 1.0
    s_phase: list[float] | None = None
    #: the last state's rays (:meth:`rays`): the solver asks for the residuals and then the
    #: Jacobian at the same state, and undistorting is the costly part of both
    _rays_of: tuple[bytes, list[F64]] | None = field(default=None, init=False, repr=False)

    @property
    def o_pose(self) -> int:
        """Index of the first pose parameter in the state (after projector and camera)."""
        return 8 + 4 + len(self.free)

    def camera(self, x: F64) -> tuple[F64, F64]:
        """The state's camera matrix (3, 3) and distortion (5,)."""
        c = x[8:self.o_pose]
        k = np.array([[c[0], 0.0, c[2]], [0.0, c[1], c[3]], [0.0, 0.0, 1.0]])
        d = np.array(self.dist5, np.float64)
        d[list(self.free)] = c[4:]
        return k, d

    def pose(self, x: F64, k: int) -> F64:
        """View ``k``'s (6,) rotation vector and translation in the state."""
        return x[self.o_pose + 6 * k: self.o_pose + 6 * k + 6]

    def rays(self, x: F64) -> list[F64]:
        """Per view the (m, 3) undistorted rays of its board pixels under the state's camera."""
        key = np.asarray(x[8:self.o_pose], np.float64).tobytes()
        if self._rays_of is None or self._rays_of[0] != key:
            kd = self.camera(x)
            self._rays_of = (key, [undistort_rays(p, *kd) for p in self.pix])
        return self._rays_of[1]

    def corner_res(self, x: F64, k: int, kd: tuple[F64, F64]) -> F64:
        """View ``k``'s (2n,) corner reprojection errors, px (u, v interleaved)."""
        q = self.pose(x, k)
        uv, _ = cv2.projectPoints(self.obj[k], q[:3], q[3:], kd[0], kd[1])
        return np.asarray((uv.reshape(-1, 2) - self.img[k]).ravel(), np.float64)

    def phase_res(self, x: F64, k: int, ray_k: F64) -> F64:
        """View ``k``'s (m,) phase residuals, projector px × weight, its rays ``ray_k``
        (m, 3) given (they depend on the camera alone)."""
        q = self.pose(x, k)
        pts = _plane_points(ray_k, q[:3], q[3:])
        r = _rotation(x[:3])
        den = pts @ r[2] + x[4]
        xn, yn = (pts @ r[0] + x[3]) / den, (pts @ r[1]) / den
        xp = x[5] * xn * (1.0 + x[7] * (xn * xn + yn * yn)) + x[6]
        return np.asarray(self.wts[k] * (self.xps[k] - xp), np.float64)

    def residuals(self, x: F64, rays: list[F64] | None = None) -> F64:
        """All residuals, each over its noise scale; ``rays``: :meth:`rays` of ``x`` if known."""
        kd = self.camera(x)
        rays = self.rays(x) if rays is None else rays
        s_phase = self.s_phase or [1.0] * len(self.pix)
        parts = [self.corner_res(x, k, kd) / self.s_corner for k in range(len(self.obj))]
        parts += [self.phase_res(x, k, rays[k]) / s_phase[k] for k in range(len(self.pix))]
        return np.concatenate(parts)

    def jacobian(self, x: F64) -> F64:
        """(residuals, state) exact derivatives of :meth:`residuals`: the corners' from
        ``cv2.projectPoints``, the phase's by the chain rule through the board plane, the
        projector and (:func:`undistort_rays_jacobian`) the camera's undistortion."""
        nv, o_pose = len(self.obj), self.o_pose
        kd = self.camera(x)
        s_phase = self.s_phase or [1.0] * nv
        n_c = [2 * len(o) for o in self.obj]
        n_rows = sum(n_c) + sum(len(p) for p in self.pix)
        # column-major: a view of its transpose is C-contiguous for BLAS's JᵀJ
        jac = np.zeros((n_rows, x.size), order="F")
        cam_cols = [6, 7, 8, 9] + [10 + i for i in self.free]  # projectPoints' f, c, dist
        row = 0
        for k in range(nv):
            q = self.pose(x, k)
            _, jp = cv2.projectPoints(self.obj[k], q[:3], q[3:], kd[0], kd[1])
            blk = slice(row, row + n_c[k])
            jac[blk, o_pose + 6 * k: o_pose + 6 * k + 6] = jp[:, :6] / self.s_corner
            jac[blk, 8:o_pose] = jp[:, cam_cols] / self.s_corner
            row += n_c[k]
        rays = self.rays(x)
        for k in range(nv):
            blk = slice(row, row + len(rays[k]))
            jp = self.phase_jacobian(x, k, rays[k], 1.0 / s_phase[k], kd)
            jac[blk, :o_pose] = jp[:, :o_pose]
            jac[blk, o_pose + 6 * k: o_pose + 6 * k + 6] = jp[:, o_pose:]
            row += len(rays[k])
        return jac

    def phase_jacobian(self, x: F64, k: int, ray: F64, scale: float,
                       kd: tuple[F64, F64] | None = None) -> F64:
        """Derivatives of view ``k``'s phase residuals (:meth:`phase_res`) × ``scale`` at
        ``x``, its rays ``ray`` (m, 3) given: (m, 8) in the projector's parameters with ``kd``
        None (the camera held), else (m, 8 + camera's + 6): projector, camera (``kd``: its
        matrix and distortion in ``x``), then view ``k``'s pose."""
        rp, jrp = cv2.Rodrigues(np.asarray(x[:3], np.float64))
        d_rp = jrp.reshape(3, 3, 3)  # [i] = d R / d rvec_i (row-major 3 × 3)
        q = self.pose(x, k)
        rb, jrb = cv2.Rodrigues(np.asarray(q[:3], np.float64))
        n, t = rb[:, 2], q[3:]
        nt, rn = float(n @ t), ray @ n
        s = nt / rn
        pts = ray * s[:, None]
        den = pts @ rp[2] + x[4]
        xn, yn = (pts @ rp[0] + x[3]) / den, (pts @ rp[1]) / den
        w = self.wts[k] * scale
        c = w * x[5]
        r2 = xn * xn + yn * yn
        # the residual w·(x_p − f·x_n·(1 + k1·r²) − c) through x_n (a) and y_n (b)
        a = -c * (1.0 + x[7] * (r2 + 2.0 * xn * xn))
        b = -c * 2.0 * x[7] * xn * yn
        n_cam = self.o_pose - 8
        out = np.empty((len(ray), 8 if kd is None else 8 + n_cam + 6))
        # projector: rotation, t_x, t_z, focal length, principal point, k1
        for i in range(3):
            p_r2 = pts @ d_rp[i][2]
            out[:, i] = (a * (pts @ d_rp[i][0] - xn * p_r2)
                         + b * (pts @ d_rp[i][1] - yn * p_r2)) / den
        out[:, 3] = a / den
        out[:, 4] = -(a * xn + b * yn) / den
        out[:, 5] = -w * xn * (1.0 + x[7] * r2)
        out[:, 6] = -w
        out[:, 7] = -c * xn * r2
        if kd is None:
            return out
        # the board point P = ray·s, s = (n·t) / (ray·n): dr/dP, then the pose and the ray
        dr_dp = ((a / den)[:, None] * (rp[0][None, :] - xn[:, None] * rp[2][None, :])
                 + (b / den)[:, None] * (rp[1][None, :] - yn[:, None] * rp[2][None, :]))
        dr_dp_ray = np.einsum("ij,ij->i", dr_dp, ray)
        d_n = jrb.reshape(3, 3, 3)[:, :, 2]  # [i] = d n / d rvec_i
        o = 8 + n_cam
        for i in range(3):
            ds = (float(d_n[i] @ t) * rn - nt * (ray @ d_n[i])) / (rn * rn)
            out[:, o + i] = dr_dp_ray * ds
        out[:, o + 3: o + 6] = (dr_dp_ray / rn)[:, None] * n
        # camera: through the ray's x and y (its z is 1)
        dr_dray = s[:, None] * dr_dp[:, :2] - (dr_dp_ray * nt / (rn * rn))[:, None] * n[:2]
        d_ray = undistort_rays_jacobian(ray, *kd, self.free)  # (m, 2, n_cam)
        out[:, 8:o] = np.einsum("ib,ibj->ij", dr_dray, d_ray)
        return out


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
    projector_start: F64 | None = None,
    noise_scales: NoiseScales | None = None,
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
        projector_start: (8,) a projector (:attr:`RefinedPoses.projector`) the projector-only
            fit starts from instead of the direct linear start (e.g. the joint fit of all views
            when a subset of them is refitted); None: the direct linear start.
        noise_scales: the residuals' scales (one phase scale per view) — a refit of a subset of
            the views keeps its whole fit's (:attr:`RefinedPoses.noise_scales`), so that it is
            the same weighted estimator with views left out: scales estimated again at that
            fit's solution are the phase's misfit there, not its noise at the start (on
            noise-free phase 500 × smaller). None: estimated from the start's residuals.

    Returns:
        :class:`RefinedPoses`, or None when the data do not allow it (too few phase points,
        a degenerate projector start or a failed fit) — the corner calibration then stands.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    nv = len(obj)
    if noise_scales is not None and len(noise_scales.phase_px) != nv:
        raise ValueError(f"noise_scales: {len(noise_scales.phase_px)} phase scales for {nv} views")
    wts = weights if weights is not None else [np.ones(len(p)) for p in proj_x]
    keep = [np.isfinite(p) & np.isfinite(w) & (w > 0) for p, w in zip(proj_x, wts, strict=True)]
    if nv < 3 or any(int(k.sum()) < MIN_PHASE_POINTS for k in keep):
        return None
    cam = np.asarray(cam, np.float64)
    free = tuple(int(i) for i in free_dist)
    prob = JointProblem(
        [np.asarray(o, np.float64) for o in obj],
        [np.asarray(i, np.float64).reshape(-1, 2) for i in img],
        [np.asarray(q, np.float64)[k] for q, k in zip(pixels, keep, strict=True)],
        [np.asarray(p, np.float64)[k] for p, k in zip(proj_x, keep, strict=True)],
        [np.asarray(w, np.float64)[k] for w, k in zip(wts, keep, strict=True)],
        (list(np.ravel(np.asarray(dist, np.float64))) + [0.0] * 5)[:5], free)
    cam0 = np.array([cam[0, 0], cam[1, 1], cam[0, 2], cam[1, 2]] + [prob.dist5[i] for i in free])
    pose0 = np.concatenate(
        [np.concatenate([np.ravel(rv), np.ravel(tv)]) for rv, tv in zip(rvecs, tvecs, strict=True)]
    )
    o_cam = 8

    # projector start: 1-D DLT on the corner poses' board points, then its own fit
    x_init = np.concatenate([np.zeros(8), cam0, pose0])
    kd0 = prob.camera(x_init)
    # the start's camera is fixed: its rays are undistorted once, not on every evaluation
    rays0 = prob.rays(x_init)
    if projector_start is not None:
        x_init[:8] = np.asarray(projector_start, np.float64)
    else:
        x3 = np.concatenate([_plane_points(rays0[k], prob.pose(x_init, k)[:3],
                                           prob.pose(x_init, k)[3:]) for k in range(nv)])
        try:
            rot, t, f, c = _decompose(_dlt_1d(x3, np.concatenate(prob.xps)), x3)
        except (ValueError, np.linalg.LinAlgError):
            return None
        x_init[:8] = np.concatenate([Rotation.from_matrix(rot).as_rotvec(),
                                     [t[0], t[2], f, c, 0.0]])

    def proj_only(xp: F64) -> F64:
        xx = np.concatenate([xp, x_init[8:]])
        return np.concatenate([prob.phase_res(xx, k, rays0[k]) for k in range(nv)])

    def proj_only_jac(xp: F64) -> F64:
        xx = np.concatenate([xp, x_init[8:]])
        out = np.empty((sum(len(r) for r in rays0), 8), order="F")  # MINPACK's layout
        row = 0
        for k in range(nv):
            out[row:row + len(rays0[k])] = prob.phase_jacobian(xx, k, rays0[k], 1.0)
            row += len(rays0[k])
        return out

    try:
        start = least_squares(proj_only, x_init[:8], jac=proj_only_jac, method="lm",
                              x_scale="jac", max_nfev=2000)
    except (ValueError, np.linalg.LinAlgError):
        return None
    x_init[:8] = start.x
    # noise scales; phase outliers (order slips, board edges) beyond OUTLIER_SCALES dropped
    prob.s_corner = noise_scales.corner_px if noise_scales is not None else max(
        float(np.sqrt(np.mean(np.concatenate(
            [prob.corner_res(x_init, k, kd0) for k in range(nv)]) ** 2))),
        1e-3,
    )
    s_phase = []
    for k in range(nv):
        r0 = prob.phase_res(x_init, k, rays0[k])
        s = (noise_scales.phase_px[k] if noise_scales is not None
             else max(1.4826 * float(np.median(np.abs(r0))), 1e-4))
        ok = np.abs(r0) <= OUTLIER_SCALES * s
        if int(ok.sum()) < MIN_PHASE_POINTS:
            return None
        prob.pix[k], prob.xps[k], prob.wts[k] = prob.pix[k][ok], prob.xps[k][ok], prob.wts[k][ok]
        s_phase.append(s)
    prob.s_phase = s_phase
    prob._rays_of = None  # the pixels changed

    try:
        # MINPACK's steps from JᵀJ, not its unblocked QR (app.calib.levenberg): J is ~60k × 55
        x = levenberg_marquardt(prob.residuals, prob.jacobian, x_init, max_nfev=100).x
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(x)) or x[o_cam] <= 0 or x[o_cam + 1] <= 0:
        return None
    kd = prob.camera(x)
    out_r = [prob.pose(x, k)[:3].reshape(3, 1).copy() for k in range(nv)]
    out_t = [prob.pose(x, k)[3:].reshape(3, 1).copy() for k in range(nv)]
    # per corner (both coordinates), as cv2.calibrateCamera's RMS: comparable with the corner fit
    corner_all = np.concatenate([prob.corner_res(x, k, kd) for k in range(nv)])
    reproj = float(np.sqrt(2.0 * np.mean(corner_all**2)))
    change = [
        1e3
        * math.acos(
            min(1.0, abs(float(_rotation(np.ravel(a))[:, 2] @ _rotation(np.ravel(b))[:, 2])))
        )
        for a, b in zip(rvecs, out_r, strict=True)
    ]
    return RefinedPoses(kd[0], kd[1], out_r, out_t, reproj, change, x[:8].copy(),
                        NoiseScales(prob.s_corner, tuple(s_phase)))


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
