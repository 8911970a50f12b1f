"""The calibration record and its versioned JSON file (``fringescope.calibration/1``).

Eq. (5) of Le et al. (2018) maps the unwrapped phase φ at pixel (u, v) to the height
above the reference plane. It is evaluated in normalised coordinates
``u' = (u - u0) / su``, ``v' = (v - v0) / sv``, ``φ' = (φ - φ0) / sφ`` (stored in
``normalization``), with φ the unwrapped phase of the *finest* frequency in radians:

    z = (1 + c1φ' + (c2 + c3φ')u' + (c4 + c5φ')v' + (c6 + c7φ')u'² + (c8 + c9φ')v'² + (c10 + c11φ')u'v')
        / (d0 + d1φ' + (d2 + d3φ')u' + ... + (d10 + d11φ')u'v')

``numerator`` holds c1..c11 (11 values), ``denominator`` d0..d11 (12 values): 23 in all.
The reference plane is ``normal · X + offset_mm = height`` in the camera frame, the
unit normal pointing toward the scope, so the camera centre has height ``offset_mm``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app import __version__
from app.atomic import atomic_write_text
from app.core.schedule import PatternSchedule

FORMAT = "fringescope.calibration/1"
N_NUMERATOR = 11
N_DENOMINATOR = 12


@dataclass
class Calibration:
    """Everything needed to turn a fringe set into metric depth and points.

    Attributes:
        camera_matrix: (3, 3) float64 pinhole intrinsics, pixels.
        dist_coeffs: (k,) float64 OpenCV distortion coefficients (k in 4, 5, 8, 12, 14).
        image_size: (width, height) of the camera frames, pixels.
        plane_normal: (3,) unit normal of the reference plane, toward the scope.
        plane_offset_mm: height of the camera centre above the reference plane, mm.
        numerator: (11,) c1..c11 of Eq. (5).
        denominator: (12,) d0..d11 of Eq. (5).
        normalization: ``{"u": (u0, su), "v": (v0, sv), "phi": (φ0, sφ)}``.
        pattern: the fringe schedule the coefficients were fitted for.
        height_range_mm: (min, max) height spanned by the calibration poses, mm.
        pose_residuals: per pose ``{"pose", "rms_mm", "reprojection_px", "points"}``.
    """

    camera_matrix: npt.NDArray[np.float64]
    dist_coeffs: npt.NDArray[np.float64]
    image_size: tuple[int, int]
    plane_normal: npt.NDArray[np.float64]
    plane_offset_mm: float
    numerator: npt.NDArray[np.float64]
    denominator: npt.NDArray[np.float64]
    normalization: dict[str, tuple[float, float]]
    pattern: PatternSchedule = field(default_factory=PatternSchedule)
    height_range_mm: tuple[float, float] = (0.0, 20.0)
    pose_residuals: list[dict[str, Any]] = field(default_factory=list)
    created: str = field(default_factory=lambda: datetime.now(UTC).isoformat(timespec="seconds"))
    software_version: str = __version__
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.camera_matrix = _array("camera_matrix", self.camera_matrix, (3, 3))
        self.dist_coeffs = _array("dist_coeffs", self.dist_coeffs, None).ravel()
        if self.dist_coeffs.size not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"dist_coeffs: {self.dist_coeffs.size} coefficients is not an OpenCV model")
        self.plane_normal = _array("plane_normal", self.plane_normal, (3,))
        norm = float(np.linalg.norm(self.plane_normal))
        if not 0.999 < norm < 1.001:
            raise ValueError(f"plane_normal: must be a unit vector, has length {norm:.4f}")
        self.numerator = _array("numerator", self.numerator, (N_NUMERATOR,))
        self.denominator = _array("denominator", self.denominator, (N_DENOMINATOR,))
        if not math.isfinite(self.plane_offset_mm):
            raise ValueError("plane_offset_mm: must be finite")
        w, h = (int(x) for x in self.image_size)
        if w <= 0 or h <= 0:
            raise ValueError(f"image_size: invalid {self.image_size}")
        self.image_size = (w, h)
        lo, hi = (float(x) for x in self.height_range_mm)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"height_range_mm: need finite min < max, got {self.height_range_mm}")
        self.height_range_mm = (lo, hi)
        norm_out: dict[str, tuple[float, float]] = {}
        for key in ("u", "v", "phi"):
            if key not in self.normalization:
                raise ValueError(f"normalization: missing {key!r}")
            off, scale = (float(x) for x in self.normalization[key])
            if not (math.isfinite(off) and math.isfinite(scale)) or scale == 0.0:
                raise ValueError(f"normalization: {key} needs a finite offset and non-zero scale")
            norm_out[key] = (off, scale)
        self.normalization = norm_out

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

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of the calibration file."""
        return {
            **self.extra,
            "format": FORMAT,
            "software_version": self.software_version,
            "created": self.created,
            "image_size": list(self.image_size),
            "camera_matrix": self.camera_matrix.tolist(),
            "dist_coeffs": self.dist_coeffs.tolist(),
            "reference_plane": {"normal": self.plane_normal.tolist(), "offset_mm": self.plane_offset_mm},
            "model": {
                "equation": "Le2018-eq5",
                "phase": "unwrapped phase of the finest frequency, radians",
                "numerator": self.numerator.tolist(),
                "denominator": self.denominator.tolist(),
                "normalization": {k: list(v) for k, v in self.normalization.items()},
            },
            "pattern": self.pattern.to_dict(),
            "height_range_mm": list(self.height_range_mm),
            "pose_residuals": self.pose_residuals,
        }

    @classmethod
    def from_dict(cls, data: Any) -> Calibration:
        """Parse the JSON object of a calibration file; ``ValueError`` names what is wrong."""
        if not isinstance(data, dict):
            raise ValueError("calibration: expected a JSON object")
        fmt = data.get("format")
        if fmt != FORMAT:
            raise ValueError(f"calibration: unsupported format {fmt!r} (expected {FORMAT!r})")
        required = ("image_size", "camera_matrix", "dist_coeffs", "reference_plane", "model", "pattern")
        missing = [k for k in required if k not in data]
        if missing:
            raise ValueError(f"calibration: missing keys {missing}")
        model = data["model"]
        plane = data["reference_plane"]
        for obj, name, keys in (
            (model, "model", ("numerator", "denominator", "normalization")),
            (plane, "reference_plane", ("normal", "offset_mm")),
        ):
            if not isinstance(obj, dict):
                raise ValueError(f"calibration: {name} must be an object")
            miss = [k for k in keys if k not in obj]
            if miss:
                raise ValueError(f"calibration: missing keys {[f'{name}.{k}' for k in miss]}")
        known = {
            "format", "software_version", "created", "image_size", "camera_matrix", "dist_coeffs",
            "reference_plane", "model", "pattern", "height_range_mm", "pose_residuals",
        }
        try:
            return cls(
                camera_matrix=np.asarray(data["camera_matrix"], np.float64),
                dist_coeffs=np.asarray(data["dist_coeffs"], np.float64),
                image_size=tuple(data["image_size"]),  # type: ignore[arg-type]
                plane_normal=np.asarray(plane["normal"], np.float64),
                plane_offset_mm=float(plane["offset_mm"]),
                numerator=np.asarray(model["numerator"], np.float64),
                denominator=np.asarray(model["denominator"], np.float64),
                normalization={k: tuple(v) for k, v in dict(model["normalization"]).items()},
                pattern=PatternSchedule.from_dict(data["pattern"]),
                height_range_mm=tuple(data.get("height_range_mm", (0.0, 20.0))),  # type: ignore[arg-type]
                pose_residuals=list(data.get("pose_residuals", [])),
                created=str(data.get("created", "")),
                software_version=str(data.get("software_version", "")),
                extra={k: v for k, v in data.items() if k not in known},
            )
        except (TypeError, KeyError) as exc:
            raise ValueError(f"calibration: malformed value ({exc})") from None


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


def save_calibration(calibration: Calibration, path: str | os.PathLike[str]) -> Path:
    """Write ``calibration`` as JSON atomically (old file intact if this fails)."""
    return atomic_write_text(path, json.dumps(calibration.to_dict(), indent=2) + "\n")


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file; ``ValueError`` with the file name for anything wrong."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read calibration ({exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    try:
        return Calibration.from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from None
