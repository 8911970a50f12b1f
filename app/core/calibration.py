"""The calibration record: camera, reference plane, depth model and what the data support.

No file I/O here (:mod:`app.calib.calibration` reads and writes the JSON file); this module
holds the record and its JSON-object codec. Format version 2 (written) names the depth
model, its parameters and supported region, and both models' held-out-pose errors;
version 1 (Eq. (5) only) still parses.

The reference plane is ``normal · X + offset_mm = height`` in the camera frame, the unit
normal pointing toward the scope, so the camera centre has height ``offset_mm``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
import numpy.typing as npt

from app import __version__
from app.core.depth_model import DepthModel, ReferencePlane, SupportedRegion
from app.core.depth_model_registry import depth_model_from_dict
from app.core.eq5 import N_DENOMINATOR, N_NUMERATOR, Eq5Model
from app.core.schedule import PatternSchedule

FORMAT_V1 = "fringescope.calibration/1"
FORMAT = "fringescope.calibration/2"

_F64 = npt.NDArray[np.float64]

__all__ = ["FORMAT", "FORMAT_V1", "N_DENOMINATOR", "N_NUMERATOR", "Calibration"]


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


@dataclass(init=False)
class Calibration:
    """Everything needed to turn a fringe set into metric depth and points.

    Attributes:
        camera_matrix: (3, 3) float64 pinhole intrinsics, pixels.
        dist_coeffs: (k,) float64 OpenCV distortion coefficients (k in 0, 4, 5, 8, 12, 14).
        image_size: (width, height) of the camera frames, pixels.
        plane_normal: (3,) unit normal of the reference plane, toward the scope.
        plane_offset_mm: height of the camera centre above the reference plane, mm.
        model: the active :class:`~app.core.depth_model.DepthModel` (with its supported region).
        pattern: the fringe schedule the model was fitted for.
        height_range_mm: (min, max) height spanned by the calibration poses, mm.
        pose_residuals: per pose ``{"pose", "rms_mm", "reprojection_px", "points"}``.
        held_out: per model name its leave-one-pose-out errors ``{"rms_mm", "max_mm", "points"}``.

    For Eq. (5) the record can be built as in format 1, from ``numerator`` (c1..c11),
    ``denominator`` (d0..d11) and ``normalization``; ``model`` wins when given.
    """

    camera_matrix: npt.NDArray[np.float64]
    dist_coeffs: npt.NDArray[np.float64]
    image_size: tuple[int, int]
    plane_normal: npt.NDArray[np.float64]
    plane_offset_mm: float
    model: DepthModel
    pattern: PatternSchedule
    height_range_mm: tuple[float, float]
    pose_residuals: list[dict[str, Any]]
    held_out: dict[str, dict[str, Any]]
    created: str
    software_version: str
    extra: dict[str, Any]

    def __init__(
        self,
        camera_matrix: npt.ArrayLike,
        dist_coeffs: npt.ArrayLike,
        image_size: tuple[int, int],
        plane_normal: npt.ArrayLike,
        plane_offset_mm: float,
        numerator: npt.ArrayLike | None = None,
        denominator: npt.ArrayLike | None = None,
        normalization: dict[str, Any] | None = None,
        pattern: PatternSchedule | None = None,
        height_range_mm: tuple[float, float] = (0.0, 20.0),
        pose_residuals: list[dict[str, Any]] | None = None,
        created: str | None = None,
        software_version: str = __version__,
        extra: dict[str, Any] | None = None,
        *,
        model: DepthModel | None = None,
        held_out: dict[str, dict[str, Any]] | None = None,
    ) -> None:
        if model is None:
            if numerator is None or denominator is None or normalization is None:
                raise ValueError("model: give a depth model or Eq. (5)'s numerator, denominator "
                                 "and normalization")
            model = Eq5Model(np.asarray(numerator), np.asarray(denominator), dict(normalization))
        if not isinstance(model, DepthModel):
            raise ValueError("model: expected a DepthModel")
        self.model = model
        self.camera_matrix = _array("camera_matrix", camera_matrix, (3, 3))
        self.dist_coeffs = _array("dist_coeffs", dist_coeffs, None).ravel()
        if self.dist_coeffs.size not in (0, 4, 5, 8, 12, 14):
            raise ValueError(
                f"dist_coeffs: {self.dist_coeffs.size} coefficients is not an OpenCV model")
        self.plane_normal = _array("plane_normal", plane_normal, (3,))
        norm = float(np.linalg.norm(self.plane_normal))
        if not 0.999 < norm < 1.001:
            raise ValueError(f"plane_normal: must be a unit vector, has length {norm:.4f}")
        self.plane_offset_mm = float(plane_offset_mm)
        if not math.isfinite(self.plane_offset_mm):
            raise ValueError("plane_offset_mm: must be finite")
        if len(image_size) != 2 or not all(
            isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
            and float(x).is_integer() for x in image_size
        ):  # a file's true or "1384" is not a width
            raise ValueError(f"image_size: must be two integers, got {list(image_size)!r:.80}")
        w, h = (int(x) for x in image_size)
        if w <= 0 or h <= 0:
            raise ValueError(f"image_size: invalid {image_size}")
        self.image_size = (w, h)
        self.pattern = pattern if pattern is not None else PatternSchedule()
        if not isinstance(self.pattern, PatternSchedule):
            raise ValueError("pattern: expected a PatternSchedule")
        lo, hi = (float(x) for x in height_range_mm)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"height_range_mm: need finite min < max, got {height_range_mm}")
        self.height_range_mm = (lo, hi)
        self.pose_residuals = list(pose_residuals or [])
        self.held_out = dict(held_out or {})
        self.created = created if created is not None else _now()
        self.software_version = software_version
        self.extra = dict(extra or {})

    # --- Eq. (5) view (format 1 names) -------------------------------------------
    def _eq5(self) -> Eq5Model:
        if not isinstance(self.model, Eq5Model):
            raise ValueError(f"calibration: the active model is {self.model.name!r}, not 'eq5'")
        return self.model

    @property
    def numerator(self) -> npt.NDArray[np.float64]:
        """c1..c11 of the Eq. (5) model (``ValueError`` for another model)."""
        return self._eq5().numerator

    @property
    def denominator(self) -> npt.NDArray[np.float64]:
        """d0..d11 of the Eq. (5) model."""
        return self._eq5().denominator

    @property
    def normalization(self) -> dict[str, tuple[float, float]]:
        """Eq. (5)'s ``{"u": (u0, su), "v": (v0, sv), "phi": (φ0, sφ)}``."""
        return self._eq5().normalization

    @property
    def reference_plane(self) -> ReferencePlane:
        return ReferencePlane(self.plane_normal, self.plane_offset_mm)

    def height_deviations(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """(K, n) the calibration's height errors (mm) at camera-frame points (n, 3), mm, whose
        Gram matrix is their covariance: the same rows as the pixels' σ_model
        (:meth:`~app.core.depth_model.DepthModel.total_height_deviations`: for a geometric model
        the whole calibration's pose jackknife — camera and lens, reference plane, projector —
        and the alternative models' rows; the errors the calibration shares between points).
        K = 0 when it carries none. The pixel of each point is its projection through the camera
        model."""
        return self.model.total_height_deviations(*self._places(points_mm), self.reference_plane)

    def point_deviations(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """(K, n, 3) the calibration's errors (mm) of camera-frame points (n, 3), mm, whose Gram
        matrix is their covariance: the rows of :meth:`height_deviations` in 3-D
        (:meth:`~app.core.depth_model.DepthModel.total_point_deviations`), so a point moves
        sideways as well as in height where the camera's refits say so (a focal length's error
        scales a length across the view as well as along it). K = 0 when it carries none."""
        return self.model.total_point_deviations(*self._places(points_mm), self.reference_plane)

    def _places(self, points_mm: npt.ArrayLike) -> tuple[_F64, _F64, _F64, _F64]:
        """(u, v, ray_xy, height_mm) of camera-frame points (n, 3), mm: each point's pixel (its
        projection through the camera model), undistorted normalised ray (n, 2) and height above
        the reference plane."""
        x = np.asarray(points_mm, np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            ray = x[:, :2] / x[:, 2:3]
            height = x @ self.plane_normal + self.plane_offset_mm
        u, v = self.project_rays(ray)
        return u, v, ray, height

    def project_rays(self, ray_xy: npt.ArrayLike
                     ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Pixels (u, v) of undistorted normalised rays (n, 2): OpenCV's radial (k1, k2, k3; the
        rational k4..k6) and tangential (p1, p2) distortion and the camera matrix."""
        r = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        d = np.zeros(8)
        d[:min(8, self.dist_coeffs.size)] = self.dist_coeffs.ravel()[:8]
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        x, y = r[:, 0], r[:, 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        k = self.camera_matrix
        return k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]

    def check_frames(self, frames_shape: tuple[int, ...]) -> None:
        """Raise ``ValueError`` if frames of ``frames_shape`` (F, H, W) do not fit."""
        if len(frames_shape) != 3:
            raise ValueError(f"frames: expected (F, H, W), got shape {frames_shape}")
        f, h, w = frames_shape
        if (w, h) != self.image_size:
            raise ValueError(
                f"frames: image size {w}x{h} does not match the calibration's "
                f"{self.image_size[0]}x{self.image_size[1]}"
            )
        if f != self.pattern.n_frames:
            raise ValueError(f"frames: expected {self.pattern.n_frames} frames, got {f}")

    def summary(self) -> dict[str, Any]:
        """Active model, height range and held-out figures (for status and the API)."""
        return {
            "model": self.model.name,
            "height_range_mm": list(self.height_range_mm),
            "held_out": self.held_out,
        }

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of a format-2 calibration file."""
        return {
            **self.extra,
            "format": FORMAT,
            "software_version": self.software_version,
            "created": self.created,
            "image_size": list(self.image_size),
            "camera_matrix": self.camera_matrix.tolist(),
            "dist_coeffs": self.dist_coeffs.tolist(),
            "reference_plane": {"normal": self.plane_normal.tolist(),
                                "offset_mm": self.plane_offset_mm},
            "model": self.model.to_dict(),
            "held_out": self.held_out,
            "pattern": self.pattern.to_dict(),
            "height_range_mm": list(self.height_range_mm),
            "pose_residuals": self.pose_residuals,
        }

    @classmethod
    def from_dict(cls, data: Any) -> Calibration:
        """Parse a format-1 or format-2 calibration object; ``ValueError`` names what is wrong."""
        if not isinstance(data, dict):
            raise ValueError("calibration: expected a JSON object")
        fmt = data.get("format")
        if fmt not in (FORMAT, FORMAT_V1):
            raise ValueError(f"calibration: unsupported format {fmt!r} "
                             f"(expected {FORMAT!r} or {FORMAT_V1!r})")
        required = ("image_size", "camera_matrix", "dist_coeffs", "reference_plane", "model",
                    "pattern")
        missing = [k for k in required if k not in data]
        if missing:
            raise ValueError(f"calibration: missing keys {missing}")
        model = data["model"]
        plane = data["reference_plane"]
        for obj, name in ((model, "model"), (plane, "reference_plane")):
            if not isinstance(obj, dict):
                raise ValueError(f"calibration: {name} must be an object")
        miss = [k for k in ("normal", "offset_mm") if k not in plane]
        if miss:
            raise ValueError(f"calibration: missing keys {[f'reference_plane.{k}' for k in miss]}")
        known = {
            "format", "software_version", "created", "image_size", "camera_matrix", "dist_coeffs",
            "reference_plane", "model", "pattern", "height_range_mm", "pose_residuals", "held_out",
        }
        try:
            if fmt == FORMAT_V1:
                depth_model: DepthModel = Eq5Model.from_params(model, SupportedRegion())
            else:
                depth_model = depth_model_from_dict(model)
            held = data.get("held_out", {})
            if not isinstance(held, dict):
                raise ValueError("held_out: expected an object")
            return cls(
                camera_matrix=np.asarray(data["camera_matrix"], np.float64),
                dist_coeffs=np.asarray(data["dist_coeffs"], np.float64),
                image_size=tuple(data["image_size"]),
                plane_normal=np.asarray(plane["normal"], np.float64),
                plane_offset_mm=float(plane["offset_mm"]),
                model=depth_model,
                pattern=PatternSchedule.from_dict(data["pattern"]),
                height_range_mm=tuple(data.get("height_range_mm", (0.0, 20.0))),
                pose_residuals=list(data.get("pose_residuals", [])),
                held_out=held,
                created=str(data.get("created", "")),
                software_version=str(data.get("software_version", "")),
                extra={k: v for k, v in data.items() if k not in known},
            )
        except (TypeError, KeyError) as exc:
            raise ValueError(f"calibration: malformed value ({exc})") from None
        except ValueError as exc:
            msg = str(exc)
            named = msg if msg.startswith("calibration:") else f"calibration: {msg}"
            raise ValueError(named) from None


def _array(name: str, value: Any, shape: tuple[int, ...] | None) -> npt.NDArray[np.float64]:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: not a numeric array") from None
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return arr

