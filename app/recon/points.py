"""Camera rays and 3-D points from heights above the reference plane.

Every pixel's ray ``r = (x, y, 1)`` comes from undistorting its pixel coordinate
(``cv2.undistortPoints`` with the calibration's camera matrix and distortion). The
point of height ``h`` on it lies on the plane parallel to the reference plane,
``n·X + offset = h``: ``X = t·r`` with ``t = (h − offset) / (n·r)``.

A result's points are made on demand (:class:`PointRays`, :class:`LazyPoints`): most sets
are only looked at as depth, and the (H, W, 3) float32 points are a larger write than all
the other per-pixel outputs together.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, overload

import cv2
import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration

_points_kernel: Callable[..., None] | None
try:  # one compiled pass; numpy (the same values) where numba is missing
    from app.recon.fast import points_kernel as _points_kernel
except ImportError:
    _points_kernel = None


@dataclass(frozen=True)
class RayTables:
    """Per-pixel undistorted rays for one image size.

    Attributes:
        rx, ry: (H, W) normalised ray direction components (the z component is 1).
        inv_m: (H, W) 1 / (n·r) for the reference-plane normal n (NaN if the ray is
            parallel to the plane).
    """

    rx: npt.NDArray[Any]
    ry: npt.NDArray[Any]
    inv_m: npt.NDArray[Any]


def ray_tables(
    camera_matrix: npt.ArrayLike,
    dist_coeffs: npt.ArrayLike,
    image_size: tuple[int, int],
    plane_normal: npt.ArrayLike,
    *,
    dtype: Any = np.float64,
) -> RayTables:
    """Undistorted ray of every pixel of a ``(width, height)`` image.

    Args:
        camera_matrix: (3, 3) intrinsics, pixels.
        dist_coeffs: OpenCV distortion coefficients (may be empty).
        image_size: (width, height) pixels.
        plane_normal: (3,) unit normal of the reference plane, camera frame.
        dtype: float dtype of the tables.
    """
    k = np.asarray(camera_matrix, dtype=np.float64)
    dist = np.asarray(dist_coeffs, dtype=np.float64).ravel()
    n = np.asarray(plane_normal, dtype=np.float64).ravel()
    if k.shape != (3, 3) or not np.all(np.isfinite(k)):
        raise ValueError(f"camera_matrix: need a finite (3, 3) matrix, got shape {k.shape}")
    if not np.all(np.isfinite(dist)):
        raise ValueError("dist_coeffs: contains NaN or infinity")
    if n.shape != (3,) or not np.all(np.isfinite(n)):
        raise ValueError(f"plane_normal: need 3 finite values, got shape {n.shape}")
    w, h = (int(x) for x in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size: invalid {image_size}")
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1)[:, None, :]
    und = _undistort(pix, k, dist if dist.size else None).reshape(h, w, 2)
    rx, ry = und[..., 0], und[..., 1]
    m = n[0] * rx + n[1] * ry + n[2]
    with np.errstate(divide="ignore"):
        inv_m = np.where(np.abs(m) > 1e-12, 1.0 / np.where(m == 0, 1.0, m), np.nan)
    return RayTables(*(np.ascontiguousarray(a, dtype=dtype) for a in (rx, ry, inv_m)))


def _undistort(pix: npt.NDArray[np.float64], k: npt.NDArray[np.float64], dist: Any) -> Any:
    # iterate to convergence (the default 5 iterations leave ~1e-4 px with strong distortion)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        return cv2.undistortPoints(pix, k, dist, None, None, criteria=criteria)
    except (TypeError, cv2.error):  # OpenCV builds without the criteria argument
        return cv2.undistortPoints(pix, k, dist)


def calibration_ray_tables(calibration: Calibration, *, dtype: Any = np.float64) -> RayTables:
    """:func:`ray_tables` for a :class:`~app.core.calibration.Calibration`."""
    return ray_tables(
        calibration.camera_matrix, calibration.dist_coeffs, calibration.image_size,
        calibration.plane_normal, dtype=dtype,
    )


def ray_quotients(rays: RayTables, *, dtype: Any = np.float32) -> npt.NDArray[Any]:
    """(H, W, 3) ``(x, y, 1)/(n·r)`` per pixel (float32 by default): a point is
    ``(h − offset)`` times it."""
    inv_m = np.asarray(rays.inv_m, np.float64)
    q = np.stack([np.asarray(rays.rx, np.float64) * inv_m, np.asarray(rays.ry, np.float64) * inv_m,
                  inv_m], axis=-1)
    return np.ascontiguousarray(q, dtype=dtype)


def points_from_height(
    height_mm: npt.ArrayLike, rays: RayTables, plane_offset_mm: float
) -> npt.NDArray[np.float64]:
    """3-D camera-frame points of pixels with known heights.

    Args:
        height_mm: (H, W) heights above the reference plane, mm (NaN → NaN point).
        rays: ray tables of the image size.
        plane_offset_mm: the reference plane's offset (camera-centre height), mm.

    Returns:
        (H, W, 3) float64 points (x right, y down, z along the optical axis), mm.
    """
    h = np.asarray(height_mm, dtype=np.float64)
    if h.shape != rays.rx.shape:
        raise ValueError(f"height_mm: shape {h.shape} does not match the ray "
                         f"tables' {rays.rx.shape}")
    t = (h - plane_offset_mm) * rays.inv_m
    return np.stack([t * rays.rx, t * rays.ry, t], axis=-1)


@dataclass(frozen=True, eq=False)
class PointRays:
    """What turns a height map into points: ``ray_q`` (H, W, 3) float32, the
    :func:`ray_quotients` ``(x, y, 1)/(n·r)`` of every pixel, and the reference plane's
    ``offset_mm`` (float32): a point is ``(h − offset)·q``."""

    ray_q: npt.NDArray[np.float32]
    offset_mm: np.float32

    def points(self, height_mm: npt.NDArray[np.float32],
               out: npt.NDArray[np.float32] | None = None) -> npt.NDArray[np.float32]:
        """(H, W, 3) float32 camera-frame points, mm, of (H, W) float32 heights (NaN → NaN),
        in float32 arithmetic (the fused kernel's depth gives the points it used to write);
        into ``out`` when it is a C-contiguous (H, W, 3) float32 array."""
        h = np.asarray(height_mm)
        if h.dtype != np.float32 or h.shape != self.ray_q.shape[:2]:
            raise ValueError(f"height_mm: need float32 {self.ray_q.shape[:2]}, got "
                             f"{h.dtype} {h.shape}")
        if (out is None or out.shape != self.ray_q.shape or out.dtype != np.float32
                or not out.flags.c_contiguous):
            out = np.empty(self.ray_q.shape, np.float32)
        if _points_kernel is not None:
            _points_kernel(np.ascontiguousarray(h), self.ray_q, np.float32(self.offset_mm), out)
            return out
        t = np.subtract(h, self.offset_mm, dtype=np.float32)  # the same values, slower
        np.multiply(t[..., None], self.ray_q, out=out)
        return out


class _PointsOwner(Protocol):
    """A result whose ``points`` are a :class:`LazyPoints` field."""

    depth: npt.NDArray[np.float32]
    point_rays: PointRays | None


class LazyPoints:
    """A result's ``points`` field (a data descriptor): (H, W, 3) float32, mm, NaN invalid.

    Set to an array, it is kept as given. Set to None (the field's default), the points are
    made on the first read from the owner's ``depth`` and ``point_rays``
    (:meth:`PointRays.points`, into the owner's ``_points_buf`` when it has one) and kept:
    computed at most once, also with readers in several threads. Reading None-set points
    of an owner without rays is an ``AttributeError``."""

    _lock = threading.Lock()  # one computation at a time: readers of one result wait for it

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> None: ...

    @overload
    def __get__(self, obj: _PointsOwner, owner: type | None = None
                ) -> npt.NDArray[np.float32]: ...

    def __get__(self, obj: _PointsOwner | None, owner: type | None = None
                ) -> npt.NDArray[np.float32] | None:
        if obj is None:
            return None  # the dataclass field's default: made on demand
        state = vars(obj)
        pts: npt.NDArray[np.float32] | None = state.get("_points")
        if pts is not None:
            return pts
        with self._lock:
            pts = state.get("_points")
            if pts is None:
                rays = obj.point_rays
                if rays is None:
                    raise AttributeError("points: neither given nor point_rays to make them")
                pts = rays.points(obj.depth, state.get("_points_buf"))
                state["_points"] = pts
            return pts

    def __set__(self, obj: _PointsOwner, value: npt.NDArray[np.float32] | None) -> None:
        vars(obj)["_points"] = value

    @staticmethod
    def given(obj: object) -> npt.NDArray[np.float32] | None:
        """The points if they exist (given or made), else None: never computes them."""
        pts: npt.NDArray[np.float32] | None = vars(obj).get("_points")
        return pts
