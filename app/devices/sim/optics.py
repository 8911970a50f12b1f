"""Geometry of the simulated rig: pinhole camera with radial distortion, pinhole projector.

Camera frame as in DESIGN.md: x right, y down, z along the optical axis, millimetres.
The projector sits ``baseline_mm`` to the right of the camera, its axis turned by
``convergence_deg`` toward the camera axis, so the two axes cross at
``baseline / tan(convergence)`` (≈ 28 mm, inside the 25–50 mm working distance).

Rig presets, by name (:func:`rig_by_name`, :data:`RIG_NAMES`):

- ``default``: the paper's rig (1384 × 1032 camera, 12° / 6 mm, mild barrel distortion, 8-bit).
- ``endoscope``: another sensor and lens (1280 × 1024, f = 1200 px), a wider triangulation
  (16° / 10 mm), endoscope-like barrel distortion k1 = −0.25 (normalised coordinates), a
  12-bit sensor, and calibration boards that cover only the central half of the field.

Variants (also by name, not among the presets): ``default-projector-defect`` and
``endoscope-projector-defect`` give the projector a defect the calibration's models lack
(:func:`projector_defect_rig`): radial lens distortion across the fringes (2-D, so a fringe
of equal phase is bent along its length) and a DMD response gamma left uncorrected (the
fringes are not sinusoidal; with N = 4 steps the harmonics leave a periodic phase error).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import numpy.typing as npt

from app.devices.sim.shading_kernels import mat3_rows, mat3_shifted_rows

F64 = npt.NDArray[np.float64]


def rotation_y(angle_deg: float) -> F64:
    """Rotation about the camera y axis (right-handed), (3, 3)."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_x(angle_deg: float) -> F64:
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def mat3(points: F64, M: F64) -> F64:
    """``points @ M`` for (…, 3) points and a (3, k) or (3,) matrix, float64, as explicit sums
    p₀·M₀ + p₁·M₁ + p₂·M₂ (left to right) in one compiled pass.

    Small-matrix BLAS calls on millions of rows are slow (and spin threads on a busy machine);
    the numpy broadcast of the same sums made three (…, k) temporaries (83 ms for an image).
    """
    p = np.asarray(points, np.float64)
    m = np.asarray(M, np.float64)
    rows = p.reshape(-1, 3)
    out = np.empty((rows.shape[0], m.shape[1] if m.ndim == 2 else 1))
    mat3_rows(rows, np.ascontiguousarray(m.reshape(3, -1)), out)
    result: F64 = out.reshape(*p.shape[:-1], m.shape[1]) if m.ndim == 2 else out.reshape(
        p.shape[:-1])
    return result


def mat3_shifted(points: F64, shift: F64, M: F64) -> F64:
    """``mat3(points - shift, M)`` without the (…, 3) difference array; bit-identical.

    points: (…, 3) float64; shift: (3,) float64; M: (3, k) float64 → (…, k) float64.
    """
    p = np.asarray(points, np.float64)
    m = np.ascontiguousarray(M, np.float64)
    rows = p.reshape(-1, 3)
    out = np.empty((rows.shape[0], m.shape[1]))
    mat3_shifted_rows(rows, np.ascontiguousarray(shift, np.float64), m, out)
    result: F64 = out.reshape(*p.shape[:-1], m.shape[1])
    return result


_RAY_CACHE: dict[bytes, F64] = {}


def _undistort(xy_d: F64, dist: F64) -> F64:
    """Invert OpenCV's k1, k2, p1, p2, k3 model on normalised coordinates (N, 2)."""
    k1, k2, p1, p2, k3 = (list(dist) + [0.0] * 5)[:5]
    x, y = xy_d[:, 0].copy(), xy_d[:, 1].copy()
    for _ in range(100):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        nx, ny = (xy_d[:, 0] - dx) / radial, (xy_d[:, 1] - dy) / radial
        done = max(np.abs(nx - x).max(initial=0.0), np.abs(ny - y).max(initial=0.0)) < 1e-12
        x, y = nx, ny
        if done:
            break
    return np.stack([x, y], -1)


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion (k1, k2, p1, p2, k3), pixel centres at integers."""

    K: F64
    dist: F64
    image_size: tuple[int, int]  # (width, height)

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    def rays(self, u: F64, v: F64) -> F64:
        """Unit-free ray directions (x, y, 1) for pixel coordinates ``u``, ``v`` (any equal shapes).

        Distortion (OpenCV model) is inverted by fixed-point iteration to < 1e-9 (normalised units).
        """
        pts = np.stack([np.asarray(u, np.float64).ravel(), np.asarray(v, np.float64).ravel()], -1)
        xy = np.empty_like(pts)
        xy[:, 0] = (pts[:, 0] - self.K[0, 2]) / self.K[0, 0]
        xy[:, 1] = (pts[:, 1] - self.K[1, 2]) / self.K[1, 1]
        if np.any(self.dist != 0):
            xy = _undistort(xy, self.dist)
        out = np.ones((pts.shape[0], 3))
        out[:, :2] = xy
        return out.reshape(*np.shape(u), 3)

    def pixel_rays(self) -> F64:
        """Rays of every pixel centre, (H, W, 3) float64, z component 1."""
        key = self.K.tobytes() + self.dist.tobytes() + bytes(str(self.image_size), "ascii")
        if key not in _RAY_CACHE:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
            _RAY_CACHE.clear()  # keep one camera's rays (34 MB)
            _RAY_CACHE[key] = self.rays(u, v)
            _RAY_CACHE[key].setflags(write=False)
        return _RAY_CACHE[key]

    def project(self, points: F64) -> F64:
        """Pixel coordinates (…, 2) of camera-frame points (…, 3), with distortion."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        uv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.dist)
        return np.asarray(uv, np.float64).reshape(*np.shape(points)[:-1], 2)


@dataclass(frozen=True)
class ProjectorModel:
    """Pinhole projector: ``R`` maps projector-frame vectors to the camera
    frame, ``centre`` in mm."""

    K: F64
    R: F64
    centre: F64
    size: tuple[int, int] = (608, 684)  # (width, height) of the DMD
    # radial lens distortion (k1, k2) in normalised projector coordinates; (0, 0) = pinhole.
    # Applied where frames of static scenes are rendered (column/row); the moving-scene
    # kernels use the pinhole coefficients (:meth:`column_coefficients`) and ignore it.
    radial: tuple[float, float] = (0.0, 0.0)

    def to_projector(self, points: F64) -> F64:
        """Camera-frame points (…, 3) in the projector frame."""
        return mat3_shifted(points, self.centre, self.R)

    def _distortion(self, q: F64) -> F64 | float:
        """Radial factor 1 + k1·r² + k2·r⁴ of projector-frame points q (…, 3); 1.0 if none."""
        k1, k2 = self.radial
        if k1 == 0.0 and k2 == 0.0:
            return 1.0
        with np.errstate(invalid="ignore", divide="ignore"):
            r2 = (q[..., 0] ** 2 + q[..., 1] ** 2) / q[..., 2] ** 2
        return np.asarray(1.0 + r2 * (k1 + k2 * r2), np.float64)

    def column(self, points: F64) -> F64:
        """Continuous projector column x_p (pixel centres at integers) of points (…, 3)."""
        q = self.to_projector(points)
        x_p: F64 = self.K[0, 0] * self._distortion(q) * q[..., 0] / q[..., 2] + self.K[0, 2]
        return x_p

    def row(self, points: F64) -> F64:
        q = self.to_projector(points)
        y_p: F64 = self.K[1, 1] * self._distortion(q) * q[..., 1] / q[..., 2] + self.K[1, 2]
        return y_p

    def column_coefficients(self) -> tuple[F64, float, F64, float]:
        """(α, α·C, γ, γ·C) with x_p = (α·X − α·C) / (γ·X − γ·C) for a camera-frame point X."""
        a = self.K[0, 0] * self.R[:, 0] + self.K[0, 2] * self.R[:, 2]
        g = self.R[:, 2].copy()
        return a, float(a @ self.centre), g, float(g @ self.centre)

    def fringe_coordinate(self, points: F64, orientation: str = "vertical") -> F64:
        """Projector coordinate along which the fringe phase grows: column
        (vertical fringes) or row."""
        return self.column(points) if orientation == "vertical" else self.row(points)

    def fringe_coefficients(self, orientation: str = "vertical") -> tuple[F64, float, F64, float]:
        """:meth:`column_coefficients`, or for horizontal fringes the same for the projector row."""
        if orientation == "vertical":
            return self.column_coefficients()
        a = self.K[1, 1] * self.R[:, 1] + self.K[1, 2] * self.R[:, 2]
        g = self.R[:, 2].copy()
        return a, float(a @ self.centre), g, float(g @ self.centre)


@dataclass(frozen=True)
class Plane:
    """``normal · X + offset_mm = height``; unit normal toward the scope (camera
    centre height = offset)."""

    normal: F64
    offset_mm: float

    def height(self, points: F64) -> F64:
        return mat3(points, self.normal) + self.offset_mm


def plane_through(point: F64, normal_toward_scope: F64) -> Plane:
    n = np.asarray(normal_toward_scope, np.float64)
    n = n / np.linalg.norm(n)
    return Plane(n, float(-n @ np.asarray(point, np.float64)))


@dataclass(frozen=True)
class SimRig:
    """The simulated laparoscope: camera, projector and the default reference plane.

    Attributes:
        camera: intrinsics ``K`` (3×3), ``dist`` (5,), ``image_size`` (1384, 1032).
        projector: DLP3000 pinhole model and pose in the camera frame.
        reference: the reference plane (calibration pose 0) in the camera frame.
        reference_point_mm: where the camera axis meets the reference plane.
        focus_mm, blur_per_inv_mm: thin-lens defocus, blur diameter (px) = blur_per_inv_mm·|1/z −
        1/focus|.
    """

    camera: CameraModel
    projector: ProjectorModel
    reference: Plane
    reference_point_mm: F64
    focus_mm: float = 33.5
    blur_per_inv_mm: float = 200.0
    projector_focus_mm: float = 35.0
    projector_blur_per_inv_mm: float = 60.0
    extra: dict[str, float] = field(default_factory=dict)
    name: str = "default"
    # the sensor's native ADC depth: offline rendering uses it unless told otherwise
    bit_depth: int = 8
    # simulated calibration boards cover only the central half of the field
    partial_boards: bool = False
    # DMD response exponent, uncorrected (1 = linear, the LightCrafter's)
    projector_gamma: float = 1.0

    @property
    def K(self) -> F64:
        return self.camera.K

    @property
    def dist(self) -> F64:
        return self.camera.dist

    @property
    def image_size(self) -> tuple[int, int]:
        return self.camera.image_size


def default_rig(*, distortion: bool = True) -> SimRig:
    """The rig used by every scene: ~56° diagonal camera field, 12° / 6 mm stereo geometry."""
    f_px = 1650.0
    K = np.array([[f_px, 0.0, 691.5], [0.0, f_px, 515.5], [0.0, 0.0, 1.0]])
    dist = np.array([-0.05, 0.0, 0.0, 0.0, 0.0]) if distortion else np.zeros(5)
    camera = CameraModel(K, dist, (1384, 1032))
    # Projector: 500 px focal length (≈ 63° across its 608 columns) so its field covers the
    # camera's over the whole working distance; square DMD pixels, centred principal point.
    Kp = np.array([[500.0, 0.0, 303.5], [0.0, 500.0, 341.5], [0.0, 0.0, 1.0]])
    projector = ProjectorModel(Kp, rotation_y(-12.0), np.array([6.0, 0.0, 0.0]))
    # Reference plane (pose 0): 45 mm along the axis, tilted a little as a hand-placed board is.
    normal = rotation_x(4.0) @ rotation_y(-3.0) @ np.array([0.0, 0.0, -1.0])
    point = np.array([0.0, 0.0, 45.0])
    return SimRig(camera, projector, plane_through(point, normal), point)


def endoscope_rig(*, distortion: bool = True) -> SimRig:
    """A second rig: conditions the default one lacks.

    1280 × 1024 sensor, f = 1200 px, principal point a little off centre; endoscope-like
    barrel distortion k1 = −0.25 in normalised coordinates (monotonic out to the image
    corners, r_d ≈ 0.68); the projector 10 mm to the right turned 16° toward the camera
    (triangulation ≈ 14° at the reference plane against the default's ≈ 8°), with a wider
    field (f = 380 px) so it lights the camera's field over the working distance; a 12-bit
    sensor; reference plane 40 mm away; partial calibration boards by default.
    """
    f_px = 1200.0
    K = np.array([[f_px, 0.0, 645.0], [0.0, f_px, 508.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.25, 0.0, 0.0, 0.0, 0.0]) if distortion else np.zeros(5)
    camera = CameraModel(K, dist, (1280, 1024))
    Kp = np.array([[380.0, 0.0, 303.5], [0.0, 380.0, 341.5], [0.0, 0.0, 1.0]])
    projector = ProjectorModel(Kp, rotation_y(-16.0), np.array([10.0, 0.0, 0.0]))
    normal = rotation_x(-3.0) @ rotation_y(4.0) @ np.array([0.0, 0.0, -1.0])
    point = np.array([0.0, 0.0, 40.0])
    return SimRig(camera, projector, plane_through(point, normal), point, focus_mm=30.0,
                  blur_per_inv_mm=150.0, projector_focus_mm=32.0, name="endoscope", bit_depth=12,
                  partial_boards=True)


RIGS: dict[str, Callable[..., SimRig]] = {"default": default_rig, "endoscope": endoscope_rig}
RIG_NAMES = tuple(RIGS)


#: the projector defect of the ``*-projector-defect`` variants: radial (k1, k2) and gamma
DEFECT_RADIAL = (0.05, 0.0)
DEFECT_GAMMA = 1.1
DEFECT_SUFFIX = "-projector-defect"


def projector_defect_rig(base: SimRig, *, radial: tuple[float, float] = DEFECT_RADIAL,
                         gamma: float = DEFECT_GAMMA) -> SimRig:
    """``base`` with a projector defect the calibration's depth models lack.

    Args:
        base: the rig to alter.
        radial: the projector lens's radial distortion (k1, k2), normalised projector
            coordinates: the default k1 = 0.05 (default rig's projector) moves the DMD's edge
            columns by ≈ 5 px at its middle row and ≈ 12 px at its corners, bending each fringe
            along its length (the models' projector has at most k1 *along* the fringe axis).
        gamma: DMD response exponent left uncorrected (> 0; 1 = linear).

    Returns:
        A new :class:`SimRig` named ``<base name>-projector-defect``.
    """
    if not gamma > 0:
        raise ValueError(f"gamma: must be positive, got {gamma}")
    if not all(math.isfinite(k) for k in radial):
        raise ValueError(f"radial: need finite (k1, k2), got {radial}")
    proj = replace(base.projector, radial=(float(radial[0]), float(radial[1])))
    return replace(base, projector=proj, projector_gamma=float(gamma),
                   name=base.name + DEFECT_SUFFIX)


def rig_by_name(name: str, *, distortion: bool = True) -> SimRig:
    """The rig preset ``name`` (one of :data:`RIG_NAMES`), or a preset's projector-defect variant
    (``<preset>-projector-defect``, :func:`projector_defect_rig`); ValueError
    naming ``rig`` otherwise."""
    base = name[: -len(DEFECT_SUFFIX)] if name.endswith(DEFECT_SUFFIX) else name
    try:
        make = RIGS[base]
    except KeyError:
        raise ValueError(f"rig: unknown {name!r}; choose from {', '.join(RIG_NAMES)} "
                         f"(or a preset with {DEFECT_SUFFIX!r})") from None
    rig = make(distortion=distortion)
    return projector_defect_rig(rig) if base != name else rig
