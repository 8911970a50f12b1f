"""Scene description: a height field over a plane frame, spheres, a moving tool, rigid motion.

Every scene lives in the camera frame of :func:`app.devices.sim.optics.default_rig` and
shares its reference plane (calibration pose 0). Heights of a height field are measured
along its frame normal (toward the scope), in mm; ``s``/``t`` are in-plane coordinates, mm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.devices.sim.radiometry import material_id

F64 = npt.NDArray[np.float64]
# Printed albedo: (s, t) arrays (mm) -> factor in [0, 1] relative to the material reflectance.
PrintFn = Callable[[F64, F64], F64]


@dataclass
class HeightField:
    """Surface ``X = origin + s·e_s + t·e_t + h(s, t)·n`` sampled on a regular grid.

    Attributes:
        origin: (3,) mm; axes: (3, 3) columns e_s, e_t, n (unit, n toward the scope).
        heights: (ny, nx) float64 mm at s = s0 + i·ds (columns), t = t0 + j·ds (rows).
        material: (ny, nx) uint8 material ids (radiometry.MATERIALS).
        texture: (ny, nx) float32 albedo multiplier (vessels, pigment variation).
        printed: optional analytic print on the surface (area-integrated when rendered).
    """

    origin: F64
    axes: F64
    heights: F64
    s0: float
    t0: float
    ds: float
    material: npt.NDArray[np.uint8]
    texture: npt.NDArray[np.float32]
    printed: PrintFn | None = None

    @property
    def hmin(self) -> float:
        return float(self.heights.min())

    @property
    def hmax(self) -> float:
        return float(self.heights.max())

    def local(self, points: F64) -> F64:
        """(s, t, w) of camera-frame points (…, 3)."""
        from app.devices.sim.optics import mat3_shifted

        return mat3_shifted(np.asarray(points, np.float64), self.origin, self.axes)


@dataclass
class Sphere:
    centre: F64
    radius_mm: float
    material: str = "grey"


@dataclass
class Tool:
    """A capsule (forceps shaft and closed jaws) whose ends move with time (seconds)."""

    path: Callable[[float], tuple[F64, F64]]
    radius_mm: float = 1.2
    material: str = "metal"


@dataclass
class Scene:
    """What the simulated camera looks at.

    Attributes:
        motion: t (s) -> (3,) rigid translation (mm, camera frame) of surface and spheres;
            ``None`` for a static scene.
        tool: an independently moving tool, or ``None``.
    """

    name: str
    surface: HeightField
    spheres: list[Sphere] = field(default_factory=list)
    tool: Tool | None = None
    motion: Callable[[float], F64] | None = None
    description: str = ""

    @property
    def is_static(self) -> bool:
        return self.motion is None and self.tool is None

    def offset(self, t_s: float) -> F64:
        return np.zeros(3) if self.motion is None else np.asarray(self.motion(t_s), np.float64)


def frame_from_normal(origin: F64, normal: F64,
                      s_hint: F64 = np.array([1.0, 0.0, 0.0])) -> tuple[F64, F64]:
    """(origin, axes) of a plane frame with unit normal ``normal`` and e_s closest to ``s_hint``."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    es = s_hint - (s_hint @ n) * n
    es /= np.linalg.norm(es)
    et = np.cross(n, es)
    return np.asarray(origin, np.float64), np.stack([es, et, n], axis=1)


def flat_field(origin: F64, axes: F64, half_size_mm: float, material: str = "white",
               printed: PrintFn | None = None, ds: float = 0.5) -> HeightField:
    """A flat, bounded square (side 2·half_size_mm) — boards, targets, metrology planes."""
    n = int(round(2 * half_size_mm / ds)) + 1
    return HeightField(
        origin=origin, axes=axes, heights=np.zeros((n, n)), s0=-half_size_mm, t0=-half_size_mm,
        ds=ds, material=np.full((n, n), material_id(material), np.uint8),
        texture=np.ones((n, n), np.float32), printed=printed,
    )


def smooth_noise(shape: tuple[int, int], scale_px: float,
                 rng: np.random.Generator) -> npt.NDArray[np.float64]:
    """Zero-mean, unit-std band-limited noise (Gaussian-filtered white noise)."""
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(rng.standard_normal(shape), scale_px, mode="reflect")
    unit: npt.NDArray[np.float64] = (g - g.mean()) / (g.std() + 1e-12)
    return unit
