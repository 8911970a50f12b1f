"""The geometric phase-to-depth model: the projector as an inverse 1-D camera.

The projector is a pinhole along its fringe axis: a camera-frame point X maps to projector
coordinates ``X_p = R·X + t`` and to the normalised coordinate ``x_n = X_p,x / X_p,z``;
the lens bends it radially, ``x_n = x_d·(1 + k1·x_d²)``, and the projector column is
``x_p = f·x_d + c``. The finest fringe has phase ``φ = 2π·K·x_p / W`` (K fringes across
W projector pixels), so ``x_d = (φ − φ0)·inv_sphi`` with ``φ0 = 2πKc/W`` and
``inv_sphi = W/(2πKf)``.

The surface of equal phase is the plane ``(R0 − x_n R2)·X + (t0 − x_n t2) = 0`` (R0, R2
rows of R). On the camera ray ``X = s·r`` and with the reference plane
``n·X + off = height``, writing ``q = r/(n·r)`` (so ``n·q = 1``):

    height = [(off·R0 − t0·n)·q + x_n·(t2·n − off·R2)·q] / [R0·q − x_n·R2·q]

— linear over linear in x_n, per pixel: the kernel form of :mod:`app.core.depth_model`
with ray coefficients only and ``cubic = k1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from app.core.depth_model import (
    BoardSamples,
    DepthModel,
    HeightTables,
    ReferencePlane,
    SupportedRegion,
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


def _rotation(rvec: F64) -> F64:
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_rotvec(rvec).as_matrix(), np.float64)


@dataclass
class GeometricModel(DepthModel):
    """Projector pose and 1-D intrinsics along the fringe axis.

    Attributes:
        rvec: (3,) rotation vector camera → projector frame.
        t_mm: (3,) translation camera → projector frame (the component along the
            fringe lines is not observable and kept 0), mm.
        focal_px, principal_px: focal length and principal point along the fringe axis, px.
        k1: radial distortion of the projector lens along its fringe axis.
        projector_width_px: W; fringes: K of the finest frequency.
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

    def height_tables(self, image_size: tuple[int, int], plane: ReferencePlane) -> HeightTables:
        u_norm, rows = row_tables_zero(image_size)
        phi0, inv_sphi = self.phase_normalization()
        return HeightTables(u_norm, rows, self.plane_coefficients(plane).ravel(),
                            phi0, inv_sphi, self.k1)

    def x_normalised(self, phi: F64) -> F64:
        """Undistorted normalised projector coordinate x_n of phase φ."""
        phi0, inv_sphi = self.phase_normalization()
        xd = (np.asarray(phi, np.float64) - phi0) * inv_sphi
        return xd * (1.0 + self.k1 * xd * xd)

    def height_at(self, u: F64, v: F64, ray_xy: F64, phi: F64, plane: ReferencePlane) -> F64:
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        r = np.concatenate([rxy, np.ones((len(rxy), 1))], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = r / (r @ np.asarray(plane.normal, np.float64))[:, None]
            a0, a1, b0, b1 = (q @ self.plane_coefficients(plane).T).T
            xn = self.x_normalised(np.asarray(phi, np.float64).ravel())
            return np.asarray((a0 + a1 * xn) / (b0 + b1 * xn), np.float64)

    def params(self) -> dict[str, Any]:
        return {
            "description": "projector as an inverse 1-D camera along the fringe axis",
            "rvec": self.rvec.tolist(), "t_mm": self.t_mm.tolist(),
            "focal_px": self.focal_px, "principal_px": self.principal_px, "k1": self.k1,
            "projector_width_px": self.projector_width_px, "fringes": self.fringes,
        }

    @classmethod
    def from_params(cls, params: dict[str, Any], region: SupportedRegion) -> GeometricModel:
        keys = ("rvec", "t_mm", "focal_px", "principal_px", "k1", "projector_width_px", "fringes")
        miss = [k for k in keys if k not in params]
        if miss:
            raise ValueError(f"missing keys {[f'model.{k}' for k in miss]}")
        try:
            return cls(**{k: params[k] for k in keys}, region=region)
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

        ok = np.isfinite(samples.phi) & np.isfinite(samples.z_mm)
        if int(ok.sum()) < MIN_SAMPLES:
            raise ValueError(f"points: the geometric model needs at least {MIN_SAMPLES} control points, "
                             f"got {int(ok.sum())}")
        x3 = samples.subset(ok).points_mm(plane)
        w, k = samples.projector_width_px, samples.fringes
        xp = samples.phi[ok] * w / (2.0 * math.pi * k)
        p = _dlt_1d(x3, xp)
        rot, t, f, c = _decompose(p, x3)
        from scipy.spatial.transform import Rotation

        x0 = np.concatenate([Rotation.from_matrix(rot).as_rotvec(), [t[0], t[2], f, c, 0.0]])

        def residuals(x: F64) -> F64:
            r = _rotation(x[:3])
            xn = (x3 @ r[0] + x[3]) / (x3 @ r[2] + x[4])
            xd = (xp - x[6]) / x[5]
            return np.asarray(x[5] * (xd * (1.0 + x[7] * xd * xd) - xn), np.float64)

        def solve(sel: npt.NDArray[np.bool_], with_k1: bool) -> F64:
            def res_k(x: F64) -> F64:
                return residuals(np.concatenate([x, [0.0]]))[sel]

            if with_k1:
                r = least_squares(lambda x: residuals(x)[sel], x0, method="lm", x_scale="jac", max_nfev=5000)
                return np.asarray(r.x if np.all(np.isfinite(r.x)) else x0, np.float64)
            r = least_squares(res_k, x0[:7], method="lm", x_scale="jac", max_nfev=5000)
            return np.concatenate([r.x if np.all(np.isfinite(r.x)) else x0[:7], [0.0]])

        # Projector distortion by held-out phase: the outer parts of the boards' phase range
        # predicted by a fit to the inner part, with and without k1; k1 dropped if it predicts worse.
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
        use_k1 = not held or held[True] <= held[False]
        x = solve(everything, use_k1 or not held)
        # the field: the data's phase range, extended by the extrapolation the held-out test
        # verified (the outer parts predicted within tolerance of their in-sample error)
        margin = 0.0
        if held:
            in_sample = float(np.sqrt(np.mean(residuals(x)[~inner] ** 2)))
            if held[use_k1] <= max(PHASE_EXTRAPOLATION_TOLERANCE * in_sample, PHASE_FLOOR_PX):
                margin = half * (1.0 / PHASE_SPLIT - 1.0)
        region = SupportedRegion(phase_rad=(lo - margin, hi + margin))
        return cls(x[:3], np.array([x[3], 0.0, x[4]]), float(x[5]), float(x[6]), float(x[7]), w, k, region)


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
    mx, sx = x3.mean(axis=0), float(np.sqrt(np.mean(np.sum((x3 - x3.mean(axis=0)) ** 2, axis=1)))) or 1.0
    mp, sp = float(xp.mean()), float(xp.std()) or 1.0
    xh = np.concatenate([(x3 - mx) / sx, np.ones((len(x3), 1))], axis=1)
    xpn = (xp - mp) / sp
    a = np.concatenate([xh, -xpn[:, None] * xh], axis=1)
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise ValueError("poses: degenerate — the board points do not determine the projector geometry; "
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
