"""Point clouds as binary little-endian PLY: valid points only, float32 x y z + uchar intensity
(+ float32 ``sigma_mm``, the total 1-σ depth uncertainty, when given, and its parts
``sigma_noise_mm`` and ``sigma_model_mm``, when given)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

from app.atomic import atomic_write_bytes

VERTEX_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1")])
VERTEX_SIGMA_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"),
                               ("sigma_mm", "<f4")])
#: the optional float32 properties after ``intensity``, in file order
SIGMA_PROPERTIES = ("sigma_mm", "sigma_noise_mm", "sigma_model_mm")


def _intensity_u8(intensity: npt.NDArray[np.generic],
                  mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint8]:
    """uint8 as is; other types scaled so the largest finite value among ``mask`` maps to 255."""
    if intensity.dtype == np.uint8:
        return np.asarray(intensity[mask], dtype=np.uint8)
    vals = intensity[mask].astype(np.float64)
    finite = np.isfinite(vals)
    top = float(vals[finite].max()) if finite.any() else 0.0
    scale = 255.0 / top if top > 0 else 0.0
    return np.clip(np.rint(np.where(finite, vals, 0.0) * scale), 0, 255).astype(np.uint8)


def ply_bytes(
    points: npt.ArrayLike, valid: npt.ArrayLike, intensity: npt.ArrayLike,
    sigma: npt.ArrayLike | None = None,
    *, sigma_noise: npt.ArrayLike | None = None, sigma_model: npt.ArrayLike | None = None,
) -> bytes:
    """Encode the valid points of a depth map as a binary little-endian PLY.

    Args:
        points: (H, W, 3) camera-frame points, mm.
        valid: (H, W) bool; only these pixels (and only finite points) are written,
            in row-major order.
        intensity: (H, W) any numeric; uint8 is written as is, anything else is scaled
            so its maximum over the written pixels becomes 255.
        sigma: optional (H, W) total 1-σ depth uncertainty, mm, written as float32 ``sigma_mm``.
        sigma_noise, sigma_model: optional (H, W) its sensor-noise and calibration parts, mm,
            written as float32 ``sigma_noise_mm`` and ``sigma_model_mm``.

    Returns:
        PLY file contents: vertices with float32 ``x y z``, uchar ``intensity`` (and the float32
        σ properties given, in the order of :data:`SIGMA_PROPERTIES`).
    """
    pts = np.asarray(points)
    ok = np.asarray(valid)
    inten = np.asarray(intensity)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points: expected shape (H, W, 3), got {pts.shape}")
    if ok.shape != pts.shape[:2] or ok.dtype != np.bool_:
        raise ValueError(f"valid: expected a bool array of shape {pts.shape[:2]}, "
                         f"got {ok.dtype} {ok.shape}")
    numeric = np.issubdtype(inten.dtype, np.number) or inten.dtype == np.bool_
    if inten.shape != pts.shape[:2] or not numeric:
        raise ValueError(f"intensity: expected a numeric array of shape {pts.shape[:2]}, "
                         f"got {inten.dtype} {inten.shape}")
    sigmas: dict[str, npt.NDArray[np.generic]] = {}
    for name, arr in zip(SIGMA_PROPERTIES, (sigma, sigma_noise, sigma_model), strict=True):
        if arr is None:
            continue
        a = np.asarray(arr)
        arg = name.removesuffix("_mm")
        if a.shape != pts.shape[:2] or not np.issubdtype(a.dtype, np.floating):
            raise ValueError(f"{arg}: expected a float array of shape {pts.shape[:2]}, "
                             f"got {a.dtype} {a.shape}")
        sigmas[name] = a
    mask = ok & np.all(np.isfinite(pts), axis=2)
    verts = np.empty(int(mask.sum()), _vertex_dtype(tuple(sigmas)))
    sel = pts[mask].astype(np.float32)
    verts["x"], verts["y"], verts["z"] = sel[:, 0], sel[:, 1], sel[:, 2]
    verts["intensity"] = _intensity_u8(inten, mask)
    extra = ""
    for name, a in sigmas.items():
        verts[name] = a[mask]
        extra += f"property float {name}\n"
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment fringescope point cloud, camera frame, mm\n"
        f"element vertex {verts.size}\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar intensity\n"
        f"{extra}end_header\n"
    )
    return header.encode("ascii") + verts.tobytes()


def _vertex_dtype(sigma_names: tuple[str, ...]) -> np.dtype[np.void]:
    return np.dtype([*VERTEX_DTYPE.descr, *((n, "<f4") for n in sigma_names)])


def write_ply(
    path: str | os.PathLike[str], points: npt.ArrayLike, valid: npt.ArrayLike,
    intensity: npt.ArrayLike,
    sigma: npt.ArrayLike | None = None, *, sigma_noise: npt.ArrayLike | None = None,
    sigma_model: npt.ArrayLike | None = None,
) -> Path:
    """Write :func:`ply_bytes` to ``path`` atomically."""
    data = ply_bytes(points, valid, intensity, sigma, sigma_noise=sigma_noise,
                     sigma_model=sigma_model)
    return atomic_write_bytes(path, data)


def read_ply(path: str | os.PathLike[str]) -> npt.NDArray[np.void]:
    """Read a PLY written by :func:`write_ply` into a structured array (x, y, z, intensity and the
    σ properties it has)."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    dtype = _vertex_dtype(tuple(n for n in SIGMA_PROPERTIES if f"property float {n}" in header))
    return np.frombuffer(data, dtype, count=count, offset=end + len(b"end_header\n"))
