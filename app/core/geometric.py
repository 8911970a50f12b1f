"""The geometric phase-to-depth model: the projector as an inverse camera seen through its fringes.

The projector is a pinhole: a camera-frame point X maps to projector coordinates
``X_p = R·X + t`` and to normalised coordinates ``x_n = X_p,x / X_p,z`` (along the fringe axis)
and ``y_n = X_p,y / X_p,z`` (across it); the lens bends them radially as OpenCV's camera model
does, ``(x_d, y_d) = (x_n, y_n)·(1 + k1·(x_n² + y_n²))``, and the projector column is
``x_p = f·x_d + c``. The finest fringe has phase ``φ = 2π·K·x_p / W`` (K fringes across
W projector pixels), so ``x_d = (φ − φ0)·inv_sphi`` with ``φ0 = 2πKc/W`` and
``inv_sphi = W/(2πKf)``. Only x_d is measured: ``t_y`` (the projector centre's offset across
the fringes) shows only through the lens's bending, so it is fitted with a radial k1 and kept 0
without one (a pinhole's heights do not depend on it). Held at 0, a projector 2 mm off the
camera's epipolar plane left 0.03 mm errors in the image corners on the analytic rig.

The surface of equal phase is the plane ``(R0 − x_n R2)·X + (t0 − x_n t2) = 0`` (R0, R2
rows of R). On the camera ray ``X = s·r`` and with the reference plane
``n·X + off = height``, writing ``q = r/(n·r)`` (so ``n·q = 1``):

    height = [(off·R0 − t0·n)·q + x_n·(t2·n − off·R2)·q] / [R0·q − x_n·R2·q]

— linear over linear in x_n, per pixel: the kernel form of :mod:`app.core.depth_model`
with ray coefficients only and ``radial_k = k1`` on the pixel's epipolar line
``y_n = α + β·x_n`` (:meth:`GeometricModel.cross_coefficients`). Calibrations saved before the
radial lens model (no ``k1_radial`` key) bend along the fringe axis only and the other way,
``x_n = x_d·(1 + k1·x_d²)`` (``cubic = k1``), as they were fitted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from app.core.depth_model import (
    BoardSamples,
    DepthModel,
    HeightTables,
    ReferencePlane,
    SupportedRegion,
    column_term,
    epipolar_lines,
    row_tables_zero,
)

F64 = npt.NDArray[np.float64]
MIN_SAMPLES = 20
#: the projector's k1 is judged on the boards' phase range: a fit to its central PHASE_SPLIT
#: predicts the rest; k1 is dropped (a pinhole) only if the pinhole predicts it better
PHASE_SPLIT = 0.75
#: held-out / in-sample error on the outer phases still counted as a safe extrapolation; then
#: the supported phase range is the data's, extended by the verified factor 1/PHASE_SPLIT
PHASE_EXTRAPOLATION_TOLERANCE = 1.5
PHASE_FLOOR_PX = 0.01  # projector px: held-out errors below this count as exact (noise-free data)
#: k1 is kept only when it differs from 0 at this confidence: |k1| beyond Student's t quantile
#: (G − 1 degrees of freedom) times its standard error, the error estimated by the jackknife over
#: the G board poses (a pose's points share its systematic errors, so the points are not
#: independent; the poses are)
K1_CONFIDENCE = 0.95
#: the projector's offset across the fringes (t_y) shows only through k1's bending, and as k1 → 0
#: with k1·t_y² held it becomes a spurious 1/z² term (fits ran off to t_y ~ 60 m): a Gaussian
#: prior of this fraction of the boards' mean distance from the projector keeps it physical
PROJECTOR_OFFSET_PRIOR = 0.25
#: the depth model's own uncertainty (1 σ, jackknife over poses) allowed at a supported (pixel,
#: height): the bound of the gross-error rule on a pixel's total σ
#: (``app.recon.validity.max_depth_sigma_mm()``: an error beyond 0.5 mm at most once in 1e6,
#: 0.102 mm). Below it the model's σ is part of every pixel's σ (noise ⊕ calibration), so the
#: model needs no tighter bound of its own; beyond it no pixel could pass the rule.
GROSS_ERROR_MM = 0.5
GROSS_ERROR_RATE = 1e-6
MODEL_SIGMA_TOLERANCE_MM = GROSS_ERROR_MM / NormalDist().inv_cdf(1.0 - GROSS_ERROR_RATE / 2.0)
#: per side: the pixels of a cell tested by :meth:`GeometricModel.verified_region`
CELL_TEST_PIXELS = 3


def _rotation(rvec: F64) -> F64:
    return _rotation_and_derivatives(rvec)[0]


def _rotation_and_derivatives(rvec: F64) -> tuple[F64, F64]:
    """The rotation matrix (3, 3) of a rotation vector (3,) rad and its derivatives (3, 3, 3):
    ``[i]`` is d R / d rvec_i (OpenCV's Rodrigues)."""
    import cv2

    rot, jac = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))
    return np.asarray(rot, np.float64), np.asarray(jac, np.float64).reshape(3, 3, 3)


@dataclass
class GeometricModel(DepthModel):
    """Projector pose, intrinsics along the fringe axis and the lens's radial distortion.

    Attributes:
        rvec: (3,) rotation vector camera → projector frame.
        t_mm: (3,) translation camera → projector frame, mm (the component along the fringe
            lines is fitted with a radial k1, else 0).
        focal_px, principal_px: focal length and principal point along the fringe axis, px.
        k1: radial distortion of the projector lens (normalised coordinates, ray → pattern).
        projector_width_px: W; fringes: K of the finest frequency.
        k1_radial: k1 is OpenCV's radial term on ``x_n² + y_n²`` (a real lens); False:
            ``x_n = x_d·(1 + k1·x_d²)`` along the fringe axis only (the model of calibrations
            saved before, kept for them).
    """

    name: ClassVar[str] = "geometric"
    rvec: F64
    t_mm: F64
    focal_px: float
    principal_px: float
    k1: float
    projector_width_px: int
    fringes: int
    region: SupportedRegion = field(default_factory=SupportedRegion)
    k1_radial: bool = True
    #: the fits with one board pose left out each (set by :meth:`fit`; saved with the model): their
    #: spread is the model's own uncertainty (:meth:`~app.core.depth_model.DepthModel.height_sigma`)
    jackknife: list[GeometricModel] = field(default_factory=list, repr=False, compare=False)
    #: the other projector model fitted to the same data (with k1 for a pinhole, a pinhole for
    #: k1; set by :meth:`fit`): where the two disagree, the choice is uncertain
    alternative: GeometricModel | None = field(default=None, repr=False, compare=False)
    alternative_weight: float = field(default=1.0, repr=False, compare=False)
    #: the boards' own phase range (no margin; set by :meth:`fit`, not serialised)
    data_phase_rad: tuple[float, float] | None = field(default=None, repr=False, compare=False)
    #: the whole calibration refitted with one board pose left out each (camera and lens model,
    #: reference plane, projector; set by the calibration, saved with the model): their spread is
    #: the height's uncertainty from all of them (:meth:`total_height_deviations`)
    pipeline: list[PipelineFit] = field(default_factory=list, repr=False, compare=False)
    #: the whole calibration refitted with the next camera lens model (set by the calibration,
    #: saved with the model): where its heights part from this model's, the lens model's
    #: choice is uncertain (beyond the board corners' reach)
    lens_alternative: PipelineFit | None = field(default=None, repr=False, compare=False)
    #: (cx, cy, rx, ry) px: the ellipse to which the held-out corners verified the chosen lens
    #: model's extrapolation (the :attr:`lens_alternative`'s row counts only beyond it);
    #: None: everywhere
    lens_verified_px: tuple[float, float, float, float] | None = field(
        default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.rvec = _vec("rvec", self.rvec)
        self.t_mm = _vec("t_mm", self.t_mm)
        for name in ("focal_px", "principal_px", "k1"):
            val = float(getattr(self, name))
            if not math.isfinite(val):
                raise ValueError(f"{name}: must be finite")
            setattr(self, name, val)
        if self.focal_px == 0.0:
            raise ValueError("focal_px: must be non-zero")
        self.k1_radial = bool(self.k1_radial)
        self.projector_width_px = int(self.projector_width_px)
        self.fringes = int(self.fringes)
        if self.projector_width_px <= 0 or self.fringes <= 0:
            raise ValueError("projector_width_px, fringes: must be positive")

    @property
    def rotation(self) -> F64:
        return _rotation(self.rvec)

    def phase_normalization(self) -> tuple[float, float]:
        """(φ0, inv_sphi): ``x_d = (φ − φ0)·inv_sphi``."""
        s = 2.0 * math.pi * self.fringes / self.projector_width_px
        return s * self.principal_px, 1.0 / (s * self.focal_px)

    def plane_coefficients(self, plane: ReferencePlane) -> F64:
        """(4, 3) vectors of a0, a1, b0, b1 on the ray quotient q."""
        r = self.rotation
        n = np.asarray(plane.normal, np.float64)
        off = float(plane.offset_mm)
        t0, t2 = self.t_mm[0], self.t_mm[2]
        return np.stack([off * r[0] - t0 * n, t2 * n - off * r[2], r[0], -r[2]])

    def cross_coefficients(self) -> F64:
        """(3, 3) e0, e1, d: linear forms on a camera ray whose ratios ``α = e0·r / d·r`` and
        ``β = e1·r / d·r`` give the ray's epipolar line ``y_n = α + β·x_n`` (zeros where the
        lens does not act across the fringes)."""
        if not (self.k1_radial and self.k1 != 0.0):
            return np.zeros((3, 3))
        r = self.rotation
        t0, t1, t2 = self.t_mm
        return np.stack([t1 * r[0] - t0 * r[1], t2 * r[1] - t1 * r[2], t2 * r[0] - t0 * r[2]])

    def height_tables(self, image_size: tuple[int, int], plane: ReferencePlane) -> HeightTables:
        u_norm, rows = row_tables_zero(image_size)
        phi0, inv_sphi = self.phase_normalization()
        radial = self.k1 if self.k1_radial else 0.0
        return HeightTables(u_norm, rows, self.plane_coefficients(plane).ravel(),
                            phi0, inv_sphi, 0.0 if self.k1_radial else self.k1,
                            self.cross_coefficients().ravel(), radial)

    def x_normalised(self, phi: F64, ray_xy: F64) -> F64:
        """Undistorted normalised projector coordinate x_n (n,) of phases φ (n,) seen along
        camera rays ``ray_xy`` (n, 2) (the lens's bending depends on the ray's epipolar line)."""
        phi0, inv_sphi = self.phase_normalization()
        xd = (np.asarray(phi, np.float64).ravel() - phi0) * inv_sphi
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        r = np.concatenate([rxy, np.ones((len(rxy), 1))], axis=1)
        alpha, beta = epipolar_lines(self.cross_coefficients(), r)
        t, _ = column_term(xd, 0.0 if self.k1_radial else self.k1, alpha, beta,
                           self.k1 if self.k1_radial else 0.0, iterations=5)
        return t

    def height_at(self, u: F64, v: F64, ray_xy: F64, phi: F64, plane: ReferencePlane) -> F64:
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        r = np.concatenate([rxy, np.ones((len(rxy), 1))], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = r / (r @ np.asarray(plane.normal, np.float64))[:, None]
            a0, a1, b0, b1 = (q @ self.plane_coefficients(plane).T).T
            xn = self.x_normalised(np.asarray(phi, np.float64).ravel(), rxy)
            return np.asarray((a0 + a1 * xn) / (b0 + b1 * xn), np.float64)

    def distorted(self, xn: F64, yn: F64) -> F64:
        """x_d (n,) of undistorted normalised projector coordinates (x_n, y_n) (n,): the radial
        lens in closed form (a lens along the fringe axis inverted by Newton's method)."""
        xn = np.asarray(xn, np.float64)
        k1 = self.k1
        if self.k1_radial:
            yn = np.asarray(yn, np.float64)
            return np.asarray(xn * (1.0 + k1 * (xn * xn + yn * yn)), np.float64)
        xd = xn.copy()
        with np.errstate(divide="ignore", invalid="ignore"):
            for _ in range(8):
                xd = xd - (xd * (1.0 + k1 * xd * xd) - xn) / (1.0 + 3.0 * k1 * xd * xd)
        return xd

    def phase_of_points(self, points_mm: F64) -> F64:
        """(n,) finest phase (rad) this model assigns to camera-frame points (n, 3), mm: the
        inverse of the equal-phase surfaces."""
        x = np.asarray(points_mm, np.float64).reshape(-1, 3)
        r, t = self.rotation, self.t_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            z = x @ r[2] + t[2]
            xd = self.distorted((x @ r[0] + t[0]) / z, (x @ r[1] + t[1]) / z)
        phi0, inv_sphi = self.phase_normalization()
        return np.asarray(xd / inv_sphi + phi0, np.float64)

    def phase_at(self, u: F64, v: F64, ray_xy: F64, height_mm: F64, plane: ReferencePlane) -> F64:
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        h = np.broadcast_to(np.asarray(height_mm, np.float64).ravel(), (len(rxy),))
        r = np.concatenate([rxy, np.ones((len(rxy), 1))], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            pts = r * ((h - plane.offset_mm) / (r @ np.asarray(plane.normal, np.float64)))[:, None]
        return self.phase_of_points(pts)

    def total_height_deviations(self, u: F64, v: F64, ray_xy: F64, height_mm: F64,
                                plane: ReferencePlane) -> F64:
        """(K, n) height errors (mm) of the whole calibration whose Gram matrix is the covariance
        of heights above the reference plane at n (pixel, height) places: the delete-one-pose
        jackknife of :attr:`pipeline` (each refit's camera gives the pixel's ray, its plane the
        height, its projector the phase → height map), the :attr:`alternative`'s row and the
        :attr:`lens_alternative`'s row; :meth:`height_deviations` without a pipeline of at least
        3 refits."""
        return self._total_rows(u, v, ray_xy, height_mm, plane)

    def _places(self, u: F64, v: F64, ray_xy: F64, height_mm: F64, plane: ReferencePlane
                ) -> tuple[F64, F64, F64, F64, F64, F64]:
        """(rays (n, 2), u, v, heights, phases (n,), pixels (n, 2)) of n (pixel, height) places,
        the scalars broadcast to n."""
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        n = len(rxy)
        h = np.broadcast_to(np.asarray(height_mm, np.float64).ravel(), (n,))
        uu = np.broadcast_to(np.asarray(u, np.float64).ravel(), (n,))
        vv = np.broadcast_to(np.asarray(v, np.float64).ravel(), (n,))
        phi = self.phase_at(uu, vv, rxy, h, plane)
        return rxy, uu, vv, h, phi, np.stack([uu, vv], axis=1)

    def _beyond_lens_verified(self, u: F64, v: F64) -> npt.NDArray[np.bool_]:
        """Pixels (u, v) beyond :attr:`lens_verified_px` (all where it is None), where the
        :attr:`lens_alternative`'s row counts."""
        if self.lens_verified_px is None:
            return np.ones(np.shape(u), bool)
        cx, cy, rx, ry = self.lens_verified_px
        return np.asarray(((u - cx) / rx) ** 2 + ((v - cy) / ry) ** 2 > 1.0)

    def _total_rows(self, u: F64, v: F64, ray_xy: F64, height_mm: F64, plane: ReferencePlane,
                    refit_rays: list[F64] | None = None, lens_rays: F64 | None = None) -> F64:
        """:meth:`total_height_deviations`; ``refit_rays``: each refit's rays of the pixels
        (:meth:`PipelineFit.rays`), ``lens_rays``: the :attr:`lens_alternative`'s, when the
        caller reuses them over many heights."""
        g = len(self.pipeline)
        if g < 3:
            return self.height_deviations(u, v, ray_xy, height_mm, plane)
        rxy, uu, vv, h, phi, uv = self._places(u, v, ray_xy, height_mm, plane)
        if refit_rays is None:
            refit_rays = [p.rays(uv, rxy) for p in self.pipeline]
        hs = np.stack([p.projector.height_at(uu, vv, r, phi, p.plane)
                       for p, r in zip(self.pipeline, refit_rays, strict=True)])
        rows = math.sqrt((g - 1) / g) * (hs - hs.mean(axis=0))
        if self.alternative is not None:
            alt = self.alternative.height_at(uu, vv, rxy, phi, plane) - h
            rows = np.concatenate([rows, self.alternative_weight * alt[None]])
        if self.lens_alternative is not None:
            la = self.lens_alternative
            if lens_rays is None:
                lens_rays = la.rays(uv, rxy)
            lens = la.projector.height_at(uu, vv, lens_rays, phi, la.plane) - h
            lens = np.where(self._beyond_lens_verified(uu, vv), lens, 0.0)
            rows = np.concatenate([rows, lens[None]])
        return np.asarray(rows, np.float64)

    def total_point_deviations(self, u: F64, v: F64, ray_xy: F64, height_mm: F64,
                               plane: ReferencePlane) -> F64:
        """(K, n, 3) errors (mm) of the camera-frame points at n (pixel, height) places whose
        Gram matrix is their covariance, the rows of :meth:`total_height_deviations` in 3-D:
        each refit of :attr:`pipeline` puts the pixel's phase on its own camera's ray at its own
        height, so the point moves sideways (focal length, principal point, lens) as well as in
        height; the :attr:`alternative` moves it along this calibration's ray; the
        :attr:`lens_alternative` onto its own ray, beyond :attr:`lens_verified_px` only. Without
        a pipeline of at least 3: the height rows along the ray (:class:`DepthModel`)."""
        g = len(self.pipeline)
        if g < 3:
            return super().total_point_deviations(u, v, ray_xy, height_mm, plane)
        rxy, uu, vv, h, phi, uv = self._places(u, v, ray_xy, height_mm, plane)
        here = _point_on_ray(rxy, h, plane)

        def point_of(fit: PipelineFit) -> F64:
            r = fit.rays(uv, rxy)
            return _point_on_ray(r, fit.projector.height_at(uu, vv, r, phi, fit.plane), fit.plane)

        pts = np.stack([point_of(p) for p in self.pipeline])
        rows = math.sqrt((g - 1) / g) * (pts - pts.mean(axis=0))
        if self.alternative is not None:
            alt_h = self.alternative.height_at(uu, vv, rxy, phi, plane)
            rows = np.concatenate([rows, self.alternative_weight
                                   * (_point_on_ray(rxy, alt_h, plane) - here)[None]])
        if self.lens_alternative is not None:
            lens = point_of(self.lens_alternative) - here
            lens = np.where(self._beyond_lens_verified(uu, vv)[:, None], lens, 0.0)
            rows = np.concatenate([rows, lens[None]])
        return np.asarray(rows, np.float64)

    def refit(self, samples: BoardSamples, plane: ReferencePlane) -> GeometricModel:
        """This model's form (k1 free or a pinhole, as this model) refitted to ``samples`` by
        least squares from this model's parameters; no region, jackknife or alternative."""
        from scipy.optimize import least_squares

        ok = np.isfinite(samples.phi) & np.isfinite(samples.z_mm)
        if int(ok.sum()) < MIN_SAMPLES:
            raise ValueError(f"points: the geometric model needs at least {MIN_SAMPLES} control "
                             f"points, got {int(ok.sum())}")
        x3 = samples.subset(ok).points_mm(plane)
        xp = samples.phi[ok] * self.projector_width_px / (2.0 * math.pi * self.fringes)
        with_k1 = self.k1 != 0.0
        # t_y is free with a radial k1 (the bending across the fringes shows it), else 0
        n_free = (9 if self.k1_radial else 8) if with_k1 else 7
        x0 = np.array([*self.rvec, self.t_mm[0], self.t_mm[2], self.focal_px, self.principal_px,
                       self.k1, self.t_mm[1] if n_free == 9 else 0.0])

        def full(x: F64) -> F64:
            return np.concatenate([x, np.zeros(9 - len(x))])

        sol = least_squares(lambda x: _column_residuals_px(full(x), x3, xp, self.k1_radial),
                            x0[:n_free], method="lm", x_scale="jac", max_nfev=5000)
        x = full(sol.x) if np.all(np.isfinite(sol.x)) else x0
        return GeometricModel(x[:3], np.array([x[3], x[8], x[4]]), float(x[5]), float(x[6]),
                              float(x[7]), self.projector_width_px, self.fringes,
                              k1_radial=self.k1_radial)

    def to_dict(self) -> dict[str, Any]:
        out = super().to_dict()
        if self.pipeline:
            out["pipeline_jackknife"] = [p.to_dict() for p in self.pipeline]
        if self.lens_alternative is not None:
            out["lens_alternative"] = self.lens_alternative.to_dict()
            if self.lens_verified_px is not None:
                out["lens_verified_px"] = [float(x) for x in self.lens_verified_px]
        return out

    def verified_region(self, image_size: tuple[int, int], plane: ReferencePlane,
                        rays: Callable[[F64], F64], height_range_mm: tuple[float, float], *,
                        cells: tuple[int, int] = (32, 24), margin_mm: float = 2.0,
                        step_mm: float = 0.25,
                        tolerance_mm: float = MODEL_SIGMA_TOLERANCE_MM) -> SupportedRegion:
        """This model's region with each extrapolation verified to ``tolerance_mm``.

        Inside the boards' data — the calibrated height range and the boards' phase range
        (:attr:`data_phase_rad`) — the model is supported. Beyond it (other phases, heights up to
        ``margin_mm`` past the calibrated range) only where the model's own uncertainty
        (:meth:`height_sigma`: the jackknife over poses — of the whole calibration where the
        model carries it — and the
        pinhole/k1 disagreement) is within ``tolerance_mm``. Per image cell of ``cells``
        (columns, rows) a 3 × 3 set of pixels over the cell (its edges included) is tested at
        heights ``step_mm`` apart; the cell supports the contiguous run of heights, around the
        data, where every one of its pixels passes (none: the cell supports nothing); a measured
        height may pass those bounds by one step (:attr:`SupportedRegion.height_allowance_mm`).

        Args:
            image_size: (width, height) of the camera, px.
            plane: the reference plane.
            rays: maps pixels (n, 2) (u, v) to undistorted normalised rays (n, 2) (the camera
                model).
            height_range_mm: the calibrated (lo, hi) height range, mm.

        Returns:
            A :class:`SupportedRegion` with this region's field, the new height grid and the phase
            range of every verified place (this region's phase range at least); this region
            unchanged without a jackknife.
        """
        w, h = (int(x) for x in image_size)
        gw, gh = (int(x) for x in cells)
        if w <= 0 or h <= 0 or gw <= 0 or gh <= 0:
            raise ValueError(f"image_size, cells: must be positive, got {image_size}, {cells}")
        lo, hi = (float(x) for x in height_range_mm)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"height_range_mm: need finite lo < hi, got {height_range_mm}")
        if len(self.jackknife) < 3:
            return self.region
        no_data = (math.inf, -math.inf)
        p_lo, p_hi = self.data_phase_rad if self.data_phase_rad is not None else no_data
        cw, ch = w / gw, h / gh
        hs = np.arange(lo - margin_mm, hi + margin_mm + 0.5 * step_mm, step_mm)
        in_range = (hs >= lo) & (hs <= hi)
        # every cell's k × k test pixels (its edges included), all cells at once: (gh, gw, k·k)
        frac = np.linspace(0.0, 1.0, CELL_TEST_PIXELS)
        fu, fv = np.meshgrid(frac, frac)
        uu = np.clip((np.arange(gw)[None, :, None] + fu.ravel()[None, None, :]) * cw, 0, w - 1)
        vv = np.clip((np.arange(gh)[:, None, None] + fv.ravel()[None, None, :]) * ch, 0, h - 1)
        uu, vv = np.broadcast_arrays(uu, vv)
        uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
        rxy = np.asarray(rays(uv), np.float64).reshape(-1, 2)
        r3 = np.concatenate([rxy, np.ones((len(rxy), 1))], axis=1)
        nr = r3 @ np.asarray(plane.normal, np.float64)
        refit_rays = [p.rays(uv, rxy) for p in self.pipeline] if len(self.pipeline) >= 3 else None
        lens_rays = None if self.lens_alternative is None else self.lens_alternative.rays(uv, rxy)
        ok = np.empty((len(hs), gh, gw), bool)
        in_data = np.empty((len(hs), gh, gw), bool)
        # the phases the model is verified at: the boards' (with the region's margin) and every
        # tested place beyond them whose σ passes (the kernel tests each pixel's σ itself)
        no_phase = (math.inf, -math.inf)
        ph_lo, ph_hi = self.region.phase_rad if self.region.phase_rad is not None else no_phase
        for k, hk in enumerate(hs):
            with np.errstate(divide="ignore", invalid="ignore"):
                pts = r3 * ((hk - plane.offset_mm) / nr)[:, None]
            phi = self.phase_of_points(pts)
            data = bool(in_range[k]) & (phi >= p_lo) & (phi <= p_hi)
            rows = self._total_rows(uv[:, 0], uv[:, 1], rxy, np.full(len(uv), hk), plane,
                                    refit_rays, lens_rays)
            sig = (np.sqrt(np.sum(rows * rows, axis=0)) if rows.shape[0]
                   else np.full(len(uv), np.nan))
            good = data | (np.where(np.isfinite(sig), sig, np.inf) <= tolerance_mm)
            if good.any():
                ph_lo = min(ph_lo, float(np.min(phi[good])))
                ph_hi = max(ph_hi, float(np.max(phi[good])))
            ok[k] = good.reshape(gh, gw, -1).all(axis=2)
            in_data[k] = data.reshape(gh, gw, -1).any(axis=2)
        grid = np.empty((gh, gw, 2))
        for i in range(gh):
            for j in range(gw):
                okc = ok[:, i, j]
                seeds = np.flatnonzero(okc & in_data[:, i, j])
                if seeds.size == 0:
                    # no data in the cell: the verified heights nearest the calibrated range's
                    # middle
                    seeds = np.flatnonzero(okc)
                    if seeds.size == 0:
                        grid[i, j] = (1.0, -1.0)
                        continue
                    seeds = seeds[[int(np.argmin(np.abs(hs[seeds] - 0.5 * (lo + hi))))]]
                a, b = int(seeds[0]), int(seeds[-1])
                while a > 0 and okc[a - 1]:
                    a -= 1
                while b < len(hs) - 1 and okc[b + 1]:
                    b += 1
                grid[i, j] = (hs[a], hs[b])
        # the kernel tests the MEASURED height: one step of allowance for its noise (σ changes
        # little over it), else a surface on a verified end would lose half its pixels
        phase = (ph_lo, ph_hi) if ph_lo <= ph_hi else self.region.phase_rad
        return SupportedRegion(phase, grid, (cw, ch), self.region.field_px, step_mm)

    def params(self) -> dict[str, Any]:
        return {
            "description": "projector as an inverse camera along the fringe axis, its lens "
                           + ("radial" if self.k1_radial else "along the fringe axis"),
            "rvec": self.rvec.tolist(), "t_mm": self.t_mm.tolist(),
            "focal_px": self.focal_px, "principal_px": self.principal_px, "k1": self.k1,
            "k1_radial": self.k1_radial,
            "projector_width_px": self.projector_width_px, "fringes": self.fringes,
        }

    @classmethod
    def from_params(cls, params: dict[str, Any], region: SupportedRegion) -> GeometricModel:
        keys = ("rvec", "t_mm", "focal_px", "principal_px", "k1", "projector_width_px", "fringes")
        miss = [k for k in keys if k not in params]
        if miss:
            raise ValueError(f"missing keys {[f'model.{k}' for k in miss]}")
        # absent: a calibration saved before the radial lens model, fitted along the axis
        radial = params.get("k1_radial", False)
        if not isinstance(radial, bool):
            raise ValueError("model.k1_radial: must be true or false")
        try:
            return cls(**{k: params[k] for k in keys}, region=region, k1_radial=radial)
        except TypeError as exc:
            raise ValueError(f"model: malformed value ({exc})") from None

    @classmethod
    def fit(cls, samples: BoardSamples, plane: ReferencePlane) -> GeometricModel:
        """Direct linear start for the 1-D camera, then ``least_squares`` on the projector
        coordinate residual (px) over pose, focal length, principal point and k1 — k1 dropped
        when a pinhole predicts the outer phases held out of a fit to the inner ones better; the
        supported phase range is the data's, extended by the verified
        extrapolation (:data:`PHASE_SPLIT`, :data:`PHASE_EXTRAPOLATION_TOLERANCE`)."""
        from scipy.optimize import least_squares
        from scipy.stats import t as student_t

        ok = np.isfinite(samples.phi) & np.isfinite(samples.z_mm)
        if int(ok.sum()) < MIN_SAMPLES:
            raise ValueError(f"points: the geometric model needs at least {MIN_SAMPLES} control "
                             f"points, got {int(ok.sum())}")
        x3 = samples.subset(ok).points_mm(plane)
        w, k = samples.projector_width_px, samples.fringes
        xp = samples.phi[ok] * w / (2.0 * math.pi * k)
        p = _dlt_1d(x3, xp)
        rot, t, f, c = _decompose(p, x3)
        from scipy.spatial.transform import Rotation

        x0 = np.concatenate([Rotation.from_matrix(rot).as_rotvec(),
                             [t[0], t[2], f, c, 0.0, 0.0]])

        def residuals(x: F64) -> F64:
            return _column_residuals_px(x, x3, xp, True)

        prior_row = 0.0  # px per mm of t_y: set after the first (pinhole) fit

        def solve(sel: npt.NDArray[np.bool_], with_k1: bool, free_ty: bool = True) -> F64:
            # t_y shows only through k1's bending: free with k1 (under its prior), else 0
            n_free = (9 if free_ty else 8) if with_k1 else 7
            x3_sel, xp_sel = x3[sel], xp[sel]

            def res_k(x: F64) -> F64:
                r = _column_residuals_px(np.concatenate([x, np.zeros(9 - n_free)]), x3_sel,
                                         xp_sel, True)
                return np.append(r, prior_row * x[8]) if n_free == 9 else r

            def jac_k(x: F64) -> F64:
                full = _column_jacobian_px(np.concatenate([x, np.zeros(9 - n_free)]), x3_sel)
                if n_free < 9:
                    return full[:, :n_free]
                prior = np.zeros((1, 9))
                prior[0, 8] = prior_row
                return np.concatenate([full, prior])

            r = least_squares(res_k, x0[:n_free], jac=jac_k, method="lm", x_scale="jac",
                              max_nfev=5000)
            xs = r.x if np.all(np.isfinite(r.x)) else x0[:n_free]
            return np.concatenate([xs, np.zeros(9 - n_free)])

        # t_y's prior in the residuals' units: the pinhole's RMS residual per prior σ
        x_first = solve(np.ones(len(xp), bool), False)
        first_res = float(np.sqrt(np.mean(residuals(x_first) ** 2)))
        depth_mm = float(np.mean(x3 @ _rotation(x_first[:3])[2] + x_first[4]))
        prior_row = max(first_res, PHASE_FLOOR_PX) / (PROJECTOR_OFFSET_PRIOR * abs(depth_mm))
        # Projector distortion by held-out phase: the outer parts of the boards' phase range
        # predicted by a fit to the inner part, with and without k1; k1 dropped if it predicts
        # worse.
        phi = samples.phi[ok]
        lo, hi = float(np.min(phi)), float(np.max(phi))
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        inner = np.abs(phi - mid) <= PHASE_SPLIT * half
        everything = np.ones(len(phi), bool)
        held = {}
        if int(inner.sum()) >= MIN_SAMPLES and int((~inner).sum()) >= MIN_SAMPLES:
            for with_k1 in (False, True):
                xi = solve(inner, with_k1)
                held[with_k1] = float(np.sqrt(np.mean(residuals(xi)[~inner] ** 2)))
        # the jackknife over board poses: k1's standard error, and the model's own uncertainty
        pose = samples.pose[ok]
        poses = [p for p in np.unique(pose) if int((pose != p).sum()) >= MIN_SAMPLES]
        jack = {}
        if len(poses) >= 3:
            jack[True] = [solve(pose != p, True) for p in poses]
        x_k1 = solve(everything, True)
        use_k1 = not held or held[True] <= held[False]
        p_pinhole = 1.0  # the t-test's p-value of k1 = 0
        if True in jack:
            k1s = np.array([xj[7] for xj in jack[True]])
            se_k1 = math.sqrt((len(k1s) - 1) / len(k1s) * float(np.sum((k1s - k1s.mean()) ** 2)))
            t_crit = float(student_t.ppf(0.5 + 0.5 * K1_CONFIDENCE, len(k1s) - 1))
            use_k1 = use_k1 and abs(float(x_k1[7])) >= t_crit * se_k1
            t_k1 = abs(float(x_k1[7])) / se_k1 if se_k1 > 0.0 else math.inf
            p_pinhole = float(2.0 * student_t.sf(t_k1, len(k1s) - 1))
        x_pin = solve(everything, False)
        x = x_k1 if use_k1 else x_pin
        if not use_k1 and len(poses) >= 3:
            jack[False] = [solve(pose != p, False) for p in poses]
        # the field: the data's phase range, extended by the extrapolation the held-out test
        # verified (the outer parts predicted within tolerance of their in-sample error)
        margin = 0.0
        if held:
            in_sample = float(np.sqrt(np.mean(residuals(x)[~inner] ** 2)))
            if held[use_k1] <= max(PHASE_EXTRAPOLATION_TOLERANCE * in_sample, PHASE_FLOOR_PX):
                margin = half * (1.0 / PHASE_SPLIT - 1.0)
        region = SupportedRegion(phase_rad=(lo - margin, hi + margin))

        def model(xm: F64, reg: SupportedRegion) -> GeometricModel:
            return cls(xm[:3], np.array([xm[3], xm[8], xm[4]]), float(xm[5]), float(xm[6]),
                       float(xm[7]), w, k, reg)

        out = model(x, region)
        out.jackknife = [model(xj, SupportedRegion()) for xj in jack.get(use_k1, [])]
        # a k1 the data did not establish cannot place the lens's centre either: t_y held at 0
        out.alternative = model(x_pin if use_k1 else solve(everything, True, free_ty=False),
                                SupportedRegion())
        # k1 chosen: the pinhole was rejected at p, and k1's own spread is in the jackknife;
        # a pinhole chosen: k1 was not established, its whole difference may be the error
        if use_k1 and True in jack:
            out.alternative_weight = math.sqrt(p_pinhole * (1.0 - p_pinhole))
        out.data_phase_rad = (lo, hi)
        return out


@dataclass(frozen=True)
class PipelineFit:
    """One leave-one-pose-out refit of the whole calibration.

    Attributes:
        camera_matrix: (3, 3) camera intrinsics, px; dist_coeffs: (5,) OpenCV k1, k2, p1, p2, k3.
        plane: the reference plane (pose 0's board plane through this refit's camera).
        projector: the geometric model fitted to the board samples through this camera and plane.
    """

    camera_matrix: F64
    dist_coeffs: F64
    plane: ReferencePlane
    projector: GeometricModel

    def rays(self, uv: F64, start_xy: F64) -> F64:
        """(n, 2) this camera's undistorted normalised rays of pixels ``uv`` (n, 2), by Newton's
        method from ``start_xy`` (n, 2) (another camera's rays of the same pixels: close)."""
        return undistort_newton(uv, self.camera_matrix, self.dist_coeffs, start_xy)

    def height_at(self, uv: F64, start_xy: F64, phi: F64) -> F64:
        """(n,) height (mm) above this refit's plane of phases ``phi`` (n,) at pixels ``uv``."""
        rxy = self.rays(uv, start_xy)
        return self.projector.height_at(uv[:, 0], uv[:, 1], rxy, phi, self.plane)

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera_matrix": np.asarray(self.camera_matrix, np.float64).tolist(),
            "dist_coeffs": np.asarray(self.dist_coeffs, np.float64).ravel().tolist(),
            "plane_normal": np.asarray(self.plane.normal, np.float64).tolist(),
            "plane_offset_mm": float(self.plane.offset_mm),
            **self.projector.params(),
        }

    @classmethod
    def from_dict(cls, data: Any) -> PipelineFit:
        """Inverse of :meth:`to_dict`; ``ValueError`` naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError("pipeline_jackknife: expected a list of objects")
        try:
            k = np.asarray(data["camera_matrix"], np.float64)
            d = np.asarray(data["dist_coeffs"], np.float64).ravel()
            n = _vec("plane_normal", data["plane_normal"])
            off = float(data["plane_offset_mm"])
        except KeyError as exc:
            raise ValueError(f"pipeline_jackknife: missing key {exc}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"pipeline_jackknife: malformed value ({exc})") from None
        if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] == 0 or k[1, 1] == 0:
            raise ValueError("pipeline_jackknife: camera_matrix must be a finite 3x3 matrix")
        if d.size > 5 or not np.all(np.isfinite(d)) or not math.isfinite(off):
            raise ValueError("pipeline_jackknife: dist_coeffs (<= 5) and plane_offset_mm finite")
        dist = np.zeros(5)
        dist[: d.size] = d
        return cls(k, dist, ReferencePlane(n, off),
                   GeometricModel.from_params(data, SupportedRegion()))


def undistort_newton(uv: F64, camera_matrix: F64, dist_coeffs: F64, start_xy: F64,
                     iterations: int = 6) -> F64:
    """(n, 2) undistorted normalised rays of pixels ``uv`` (n, 2) through the camera
    ``camera_matrix`` (3, 3) with OpenCV's distortion ``dist_coeffs`` (k1, k2, p1, p2, k3), by
    Newton's method from ``start_xy`` (n, 2); NaN where the distortion's Jacobian is singular."""
    k = np.asarray(camera_matrix, np.float64)
    d = np.zeros(5)
    dc = np.asarray(dist_coeffs, np.float64).ravel()[:5]
    d[: dc.size] = dc
    k1, k2, p1, p2, k3 = d
    target = np.asarray(uv, np.float64).reshape(-1, 2)
    xy = np.array(start_xy, np.float64).reshape(-1, 2)
    if xy.shape != target.shape:
        raise ValueError(f"start_xy: expected shape {target.shape}, got {xy.shape}")
    for _ in range(iterations):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        j00 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
        j01 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
        j10 = j01
        j11 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
        # pixel residual through the camera matrix (skew k[0, 1]), then the 2 × 2 solve
        ru = k[0, 0] * xd + k[0, 1] * yd + k[0, 2] - target[:, 0]
        rv = k[1, 1] * yd + k[1, 2] - target[:, 1]
        a00, a01 = k[0, 0] * j00 + k[0, 1] * j10, k[0, 0] * j01 + k[0, 1] * j11
        a10, a11 = k[1, 1] * j10, k[1, 1] * j11
        with np.errstate(divide="ignore", invalid="ignore"):
            det = a00 * a11 - a01 * a10
            xy = xy - np.stack([(a11 * ru - a01 * rv) / det, (a00 * rv - a10 * ru) / det], axis=1)
    return np.asarray(xy, np.float64)


def _point_on_ray(ray_xy: F64, height_mm: F64, plane: ReferencePlane) -> F64:
    """(n, 3) camera-frame points (mm) at ``height_mm`` (n,) above ``plane`` on the undistorted
    normalised rays ``ray_xy`` (n, 2)."""
    r = np.concatenate([ray_xy, np.ones((len(ray_xy), 1))], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (height_mm - plane.offset_mm) / (r @ np.asarray(plane.normal, np.float64))
    return np.asarray(r * s[:, None], np.float64)


def _column_residuals_px(x: F64, x3: F64, xp: F64, radial: bool) -> F64:
    """(n,) projector-coordinate residuals (px) of points ``x3`` (n, 3) mm seen at projector
    coordinates ``xp`` (n,) px under the parameters ``x`` (9,): rotation vector, t_x, t_z mm,
    focal length, principal point px, k1, t_y mm (``radial``: OpenCV's radial term; else the
    inverse along x alone, without t_y)."""
    r = _rotation(x[:3])
    with np.errstate(divide="ignore", invalid="ignore"):
        z = x3 @ r[2] + x[4]
        xn = (x3 @ r[0] + x[3]) / z
        k1 = x[7]
        if radial:
            yn = (x3 @ r[1] + x[8]) / z
            return np.asarray(x[5] * xn * (1.0 + k1 * (xn * xn + yn * yn)) + x[6] - xp,
                              np.float64)
        xd = (xp - x[6]) / x[5]
        return np.asarray(x[5] * (xd * (1.0 + k1 * xd * xd) - xn), np.float64)


def _column_jacobian_px(x: F64, x3: F64) -> F64:
    """(n, 9) derivatives of :func:`_column_residuals_px` (``radial``) in its parameters ``x``
    (9,): rotation vector, t_x, t_z mm, focal length, principal point px, k1, t_y mm."""
    rot, d_rot = _rotation_and_derivatives(x[:3])
    z = x3 @ rot[2] + x[4]
    xn, yn = (x3 @ rot[0] + x[3]) / z, (x3 @ rot[1] + x[8]) / z
    f, k1 = x[5], x[7]
    rho = xn * xn + yn * yn
    # the residual f·x_n·(1 + k1·ρ) + c − x_p through x_n (a) and y_n (b)
    a = f * (1.0 + k1 * (rho + 2.0 * xn * xn))
    b = f * 2.0 * k1 * xn * yn
    out = np.empty((len(x3), 9))
    for i in range(3):
        dz = x3 @ d_rot[i][2]
        out[:, i] = (a * (x3 @ d_rot[i][0] - xn * dz) + b * (x3 @ d_rot[i][1] - yn * dz)) / z
    out[:, 3] = a / z
    out[:, 4] = -(a * xn + b * yn) / z
    out[:, 5] = xn * (1.0 + k1 * rho)
    out[:, 6] = 1.0
    out[:, 7] = f * xn * rho
    out[:, 8] = b / z
    return out


def _vec(name: str, value: Any) -> F64:
    try:
        arr = np.array(value, np.float64).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"{name}: not a numeric array") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: need 3 finite values, got shape {arr.shape}")
    return arr


def _dlt_1d(x3: F64, xp: F64) -> F64:
    """(2, 4) projection rows [p0; p2] with ``xp = p0·X̃ / p2·X̃`` (normalised DLT)."""
    mx = x3.mean(axis=0)
    sx = float(np.sqrt(np.mean(np.sum((x3 - mx) ** 2, axis=1)))) or 1.0
    mp, sp = float(xp.mean()), float(xp.std()) or 1.0
    xh = np.concatenate([(x3 - mx) / sx, np.ones((len(x3), 1))], axis=1)
    xpn = (xp - mp) / sp
    a = np.concatenate([xh, -xpn[:, None] * xh], axis=1)
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise ValueError("poses: degenerate — the board points do not determine the projector "
                         "geometry; "
                         "use more poses, tilted and spread through the volume")
    pn = vt[-1].reshape(2, 4)
    t = np.eye(4)
    t[:3, :3] /= sx
    t[:3, 3] = -mx / sx
    s = np.array([[sp, mp], [0.0, 1.0]])
    return np.asarray(s @ pn @ t, np.float64)


def _decompose(p: F64, x3: F64) -> tuple[F64, F64, float, float]:
    """R (3, 3), t (3,), f, c from the 1-D projection rows, the points ``x3`` in front."""
    p = p / np.linalg.norm(p[1, :3])
    if float(np.median(x3 @ p[1, :3] + p[1, 3])) < 0:  # the rows' sign: points in front
        p = -p
    r2, t2 = p[1, :3], p[1, 3]
    c = float(p[0, :3] @ r2)
    v = p[0, :3] - c * r2
    f = float(np.linalg.norm(v))
    r0 = v / f
    t0 = (p[0, 3] - c * t2) / f
    r1 = np.cross(r2, r0)
    rot = np.stack([r0, r1, r2])
    return rot, np.array([t0, 0.0, t2]), f, c
