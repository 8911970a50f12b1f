"""A closed-form camera–projector rig whose phase-to-height map is Eq. (5) exactly.

A test and benchmark oracle (like :mod:`app.devices.sim.ideal`); the product never uses it.

Pinhole camera K (no distortion) at the origin looking along +z; pinhole projector with
3×4 matrix P; reference plane ``n·X + off = h``. For the camera ray ``X = t·r`` the
projector column is ``x_p = (a t + b)/(c t + d)`` with ``a = P[0,:3]·r``, ``b = P[0,3]``,
``c = P[2,:3]·r``, ``d = P[2,3]`` (a, c linear in u, v), and with ``m = n·r``

    h = [off·(c x_p − a) + m·(b − d x_p)] / (c x_p − a)

— Eq. (5) with its quadratic terms zero. Writing ``x_p = s·φ``
(φ = 2π k_max x_p / w the finest phase) gives numerator and denominator bilinear in
(1, u, v) × (1, φ); substituting the normalised u', v', φ' yields the 23 coefficients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration
from app.core.geometric import GeometricModel
from app.core.schedule import PatternSchedule

F64 = npt.NDArray[np.float64]


def _look_at(center: F64, target: F64) -> F64:
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


@dataclass
class Rig:
    """Camera (width × height px) and projector geometry, all in mm / px."""

    width: int = 160
    height: int = 120
    focal_px: float = 200.0
    projector_focal_px: float = 450.0
    projector_center_mm: tuple[float, float, float] = (10.0, 0.0, 0.0)
    projector_target_mm: tuple[float, float, float] = (0.0, 0.0, 45.0)
    plane_normal: tuple[float, float, float] = (0.05, -0.03, -1.0)
    plane_offset_mm: float = 60.0
    schedule: PatternSchedule = field(default_factory=PatternSchedule)

    def __post_init__(self) -> None:
        n = np.asarray(self.plane_normal, np.float64)
        self.n = n / np.linalg.norm(n)
        f = self.focal_px
        self.K = np.array([[f, 0.0, (self.width - 1) / 2], [0.0, f, (self.height - 1) / 2],
                           [0, 0, 1.0]])
        w, h = self.schedule.width, self.schedule.height
        fp = self.projector_focal_px
        kp = np.array([[fp, 0.0, w / 2], [0.0, fp, h / 2], [0, 0, 1.0]])
        c = np.asarray(self.projector_center_mm, np.float64)
        r = _look_at(c, np.asarray(self.projector_target_mm, np.float64))
        self.P = kp @ np.hstack([r, (-r @ c)[:, None]])

    # --- geometry -----------------------------------------------------------------
    def rays(self) -> F64:
        """(H, W, 3) camera rays K⁻¹(u, v, 1) (z component 1)."""
        uu, vv = np.meshgrid(np.arange(self.width, dtype=np.float64),
                             np.arange(self.height, dtype=np.float64))
        f, cx, cy = self.K[0, 0], self.K[0, 2], self.K[1, 2]
        return np.stack([(uu - cx) / f, (vv - cy) / f, np.ones_like(uu)], axis=-1)

    def points(self, height_mm: F64) -> F64:
        """(H, W, 3) camera-frame points of the surface with per-pixel height ``height_mm``."""
        r = self.rays()
        t = (height_mm - self.plane_offset_mm) / (r @ self.n)
        return t[..., None] * r

    def projector_column(self, height_mm: F64) -> F64:
        """(H, W) projector column x_p (px) seen by each pixel on the surface."""
        x = self.points(height_mm)
        xh = x @ self.P[:, :3].T + self.P[:, 3]
        x_p: F64 = xh[..., 0] / xh[..., 2]
        return x_p

    def finest_phase(self, height_mm: F64) -> F64:
        """(H, W) true unwrapped phase of the finest frequency, radians."""
        s = self.schedule
        return 2.0 * math.pi * s.frequencies[-1] * self.projector_column(height_mm) / s.width

    # --- Eq. (5) in closed form ---------------------------------------------------------
    def _lin(self, q: F64) -> F64:
        """q·r as (const, coef_u, coef_v) for r = ((u−cx)/f, (v−cy)/f, 1)."""
        f, cx, cy = self.K[0, 0], self.K[0, 2], self.K[1, 2]
        return np.array([q[2] - q[0] * cx / f - q[1] * cy / f, q[0] / f, q[1] / f])

    def normalization(self) -> dict[str, tuple[float, float]]:
        kmax = self.schedule.frequencies[-1]
        return {
            "u": ((self.width - 1) / 2, self.width / 2),
            "v": ((self.height - 1) / 2, self.height / 2),
            "phi": (math.pi * kmax, math.pi * kmax),
        }

    def coefficients(self) -> tuple[F64, F64]:
        """Exact (c1..c11, d0..d11) of Eq. (5) in :meth:`normalization` units."""
        a, c, m = self._lin(self.P[0, :3]), self._lin(self.P[2, :3]), self._lin(self.n)
        b, d = self.P[0, 3], self.P[2, 3]
        off = self.plane_offset_mm
        s = self.schedule.width / (2.0 * math.pi * self.schedule.frequencies[-1])
        norm = self.normalization()
        num = self._normalise(-off * a + b * m, s * (off * c - d * m), norm)
        den = self._normalise(-a, s * c, norm)
        scale = num[0]
        if abs(scale) < 1e-9 * np.abs(num).max():
            raise ValueError("rig: numerator constant vanishes; move the projector target")
        num, den = num / scale, den / scale
        zeros = np.zeros(6)
        return np.concatenate([num[1:], zeros]), np.concatenate([den, zeros])

    @staticmethod
    def _normalise(const: F64, phi: F64, norm: dict[str, tuple[float, float]]) -> F64:
        """(n0 + nu u + nv v) + φ(p0 + pu u + pv v) → [1, φ', u', u'φ', v', v'φ'] coefficients."""
        (u0, su), (v0, sv), (f0, sf) = norm["u"], norm["v"], norm["phi"]
        n0, nu, nv = const
        p0, pu, pv = phi
        p_at = p0 + pu * u0 + pv * v0
        return np.array([
            n0 + nu * u0 + nv * v0 + f0 * p_at,
            sf * p_at,
            su * (nu + f0 * pu),
            su * sf * pu,
            sv * (nv + f0 * pv),
            sv * sf * pv,
        ])

    def calibration(self, height_range_mm: tuple[float, float] = (0.0, 30.0)) -> Calibration:
        num, den = self.coefficients()
        return Calibration(
            camera_matrix=self.K,
            dist_coeffs=np.zeros(5),
            image_size=(self.width, self.height),
            plane_normal=self.n,
            plane_offset_mm=self.plane_offset_mm,
            numerator=num,
            denominator=den,
            normalization=self.normalization(),
            pattern=self.schedule,
            height_range_mm=height_range_mm,
        )

    def geometric_model(self, k1: float = 0.0) -> GeometricModel:
        """The projector (P = Kp [R | t]) as the geometric depth model, exactly (``k1`` added)."""
        fp = self.projector_focal_px
        w, h = self.schedule.width, self.schedule.height
        kp = np.array([[fp, 0.0, w / 2], [0.0, fp, h / 2], [0, 0, 1.0]])
        rt = np.linalg.solve(kp, self.P)
        from scipy.spatial.transform import Rotation  # deferred: not needed to start

        rvec = Rotation.from_matrix(rt[:, :3]).as_rotvec()
        t = rt[:, 3].copy()
        t[1] = 0.0  # not observable along the fringe lines
        # the finest count as the schedule holds it (a float: heterodyne counts are fractional)
        return GeometricModel(rvec, t, fp, w / 2, k1, w,
                              self.schedule.frequencies[-1])  # type: ignore[arg-type]

    def geometric_calibration(self,
                              height_range_mm: tuple[float, float] = (0.0, 30.0)) -> Calibration:
        """:meth:`calibration` with the geometric model instead of Eq. (5)."""
        return Calibration(self.K, np.zeros(5), (self.width, self.height), self.n,
                           self.plane_offset_mm, model=self.geometric_model(),
                           pattern=self.schedule, height_range_mm=height_range_mm)

    # --- images ---------------------------------------------------------------------
    def render(
        self,
        height_mm: F64,
        *,
        background: float | F64 = 110.0,
        amplitude: float | F64 = 90.0,
        noise: float = 0.0,
        dtype: type = np.uint8,
        rng: np.random.Generator | None = None,
        max_code: int | None = None,
    ) -> npt.NDArray[np.generic]:
        """(F, H, W) fringe frames ``A + B cos(2π k x_p / w + δ_n)`` + N(0,
        noise²), rounded, clipped."""
        s = self.schedule
        xp = self.projector_column(height_mm)
        top = max_code if max_code is not None else np.iinfo(dtype).max
        out: npt.NDArray[np.generic] = np.empty((s.n_frames, self.height, self.width), dtype)
        rng = rng or np.random.default_rng(0)
        for fi, k in enumerate(s.frequencies):
            for n in range(s.steps):
                img = background + amplitude * np.cos(2 * math.pi * k * xp / s.width
                                                      + 2 * math.pi * n / s.steps)
                if noise:
                    img = img + rng.normal(0.0, noise, img.shape)
                out[s.frame_index(fi, n)] = np.clip(np.rint(img), 0, top).astype(dtype)
        return out


def bump_surface(rig: Rig, base_mm: float = 6.0, peak_mm: float = 18.0,
                 tilt_mm: float = 4.0) -> F64:
    """A smooth (H, W) height map: a Gaussian bump on a tilted plane, mm."""
    uu, vv = np.meshgrid(np.arange(rig.width, dtype=np.float64),
                         np.arange(rig.height, dtype=np.float64))
    r2 = ((uu - rig.width * 0.55) ** 2 + (vv - rig.height * 0.45) ** 2) / (0.25 * rig.width) ** 2
    return base_mm + tilt_mm * uu / rig.width + peak_mm * np.exp(-r2)


def reason_scene(
    rig: Rig, *, dtype: type = np.uint8, noise: float = 1.0, seed: int = 0
) -> tuple[npt.NDArray[np.generic], F64, dict[str, tuple[slice, slice]]]:
    """Noisy frames of :func:`bump_surface` with one patch per failure cause.

    Returns ``(frames, height_mm, patches)``; ``patches`` maps a Reason name to the
    (rows, cols) slice where that reason must be reported. Intensities scale with the
    dtype (×16 for uint16, i.e. 12-bit data, ``max_code`` 4095).
    """
    scale = 1.0 if dtype == np.uint8 else 16.0
    top = 255 if dtype == np.uint8 else 4095
    h = bump_surface(rig)
    patches = {
        "OUTSIDE_VOLUME": (slice(5, 25), slice(5, 30)),
        "SATURATED": (slice(5, 25), slice(40, 60)),
        "LOW_MODULATION": (slice(40, 60), slice(5, 30)),
        "UNWRAP_INCONSISTENT": (slice(80, 100), slice(5, 30)),
    }
    h[patches["OUTSIDE_VOLUME"]] = 36.0  # calibrated range is (0, 30) + 2 mm margin
    rng = np.random.default_rng(seed)
    frames = rig.render(h, background=110 * scale, amplitude=90 * scale, noise=noise * scale,
                        dtype=dtype, rng=rng, max_code=top)
    # all but two shifts of the second frequency clipped: fewer than three left to fit
    n = rig.schedule.steps
    frames[n + 1 : 2 * n - 1, patches["SATURATED"][0], patches["SATURATED"][1]] = top
    flat = np.clip(np.rint(100 * scale
                           + rng.normal(0, noise * scale, (rig.schedule.n_frames, 20, 25))), 0, top)
    frames[:, patches["LOW_MODULATION"][0], patches["LOW_MODULATION"][1]] = flat.astype(dtype)
    # shift the k = 4 fringes by π (N = 4: frame n ↔ n + 2): the 1 → 4 residual becomes ≈ π
    rows, cols = patches["UNWRAP_INCONSISTENT"]
    k4 = frames[4:8, rows, cols].copy()
    frames[4:8, rows, cols] = k4[[2, 3, 0, 1]]
    return frames, h, patches
