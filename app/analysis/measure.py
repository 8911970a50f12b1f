"""Measurements in 3-D where the user clicks: length, point-to-line, depth, profile, area.

Pure functions on one result — ``points`` (H, W, 3) float mm (camera frame, NaN invalid),
``valid`` (H, W) bool and ``sigma`` (H, W) float mm (the per-pixel 1-σ *height* noise,
``ReconResult.sigma``) — and pixel coordinates ``(u, v)`` (column, row). Each returns a
:class:`Measurement`: the value in mm and its 1-σ uncertainty, propagated to first order
from the per-pixel σ.

Noise model (what the uncertainty assumes):

- A pixel's height noise moves its point along the pixel's camera ray: a height change
  ``dh`` moves ``X`` by ``X / (n·X) · dh`` (``n`` the reference-plane normal, see
  :mod:`app.recon.points`; without a calibration ``n`` is taken as the optical axis, so the
  ray's z component moves by ``dh``). The ray's direction comes from the point itself.
- Noise is independent between pixels (the sensor's shot and read noise is per pixel and
  the phase of each pixel is computed from that pixel alone). Two clicks share noise only
  when they are the same pixel; that is accounted for exactly.
- ``profile`` samples are neighbours: each sample's σ is right on its own, and the
  samples' errors are correlated through the shared reference points (the chord's ends or
  the plane's three points), not through each other.
- ``area`` does not triangulate raw pixels (pixel noise would roughen the surface and
  inflate the area by ~σ²/pitch²): it triangulates samples of the surface smoothed over a
  ``window_px`` box, on a ``window_px`` grid inside the polygon plus its edges. Its σ is the
  exact first-order propagation of every pixel's noise through the box means and the
  bilinear sampling; the expected second-order inflation from the remaining roughness
  (E|∇h|²/2 per triangle) is subtracted.

Calibration: ``calibration_sigma_mm`` (the calibration's systematic height error per point,
say) adds in quadrature a height error that is smooth, not independent: two points
``d`` mm apart share it with correlation ``exp(−d / calibration_length_mm)`` (0: independent
between points; the same pixel always shares it), so a short length or a small area
feels little of it and a large one nearly all.

Picking: a click on an invalid pixel snaps to the nearest valid pixel within ``snap_px``
(reported per point with the distance) or raises ``ValueError`` naming the point and why.
Every error names the point (1-based, in the order given) and the reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration

F64 = npt.NDArray[np.float64]
KINDS = ("length", "point_to_line", "depth", "profile", "area")
#: how many points each kind needs (profile/area: at least)
MIN_POINTS = {"length": 2, "point_to_line": 3, "depth": 4, "profile": 2, "area": 3}
EXACT_POINTS = {"length": 2, "point_to_line": 3, "depth": 4}
#: an area or profile is refused when less than this fraction of its pixels is valid
MIN_COVERAGE = 0.5


@dataclass(frozen=True)
class PickedPoint:
    """One clicked point as measured.

    Attributes:
        requested: (u, v) as given, pixels.
        pixel: (u, v) of the pixel used (the nearest valid one if ``snapped``).
        point_mm: (x, y, z) camera-frame point, mm.
        sigma_mm: the pixel's 1-σ height noise, mm (NaN if unknown).
        snapped: the requested pixel was invalid (or not a whole pixel away from ``pixel``).
        snap_px: distance from the rounded request to ``pixel``, px.
        filled: the pixel is in a hole with no valid pixel within the snap radius: its point is
            a quadratic fit of the valid points around it (``sigma_mm`` that fit's noise).
        coverage: the valid share of the pixels the point rests on (1 unless ``filled``).
    """

    requested: tuple[float, float]
    pixel: tuple[int, int]
    point_mm: tuple[float, float, float]
    sigma_mm: float
    snapped: bool
    snap_px: float
    filled: bool = False
    coverage: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return {"requested": list(self.requested), "pixel": list(self.pixel),
                "point_mm": [_j(x) for x in self.point_mm], "sigma_mm": _j(self.sigma_mm),
                "snapped": self.snapped, "snap_px": round(self.snap_px, 3), "filled": self.filled,
                "coverage": round(self.coverage, 4)}


@dataclass(frozen=True)
class ProfileSamples:
    """Every pixel along a profile's polyline.

    Attributes:
        pixels: (n, 2) int (u, v).
        distance_mm: (n,) position along the reference (chord direction, or the 3-D path
            length for a plane reference), mm; NaN where the pixel is invalid.
        height_mm: (n,) signed height over the reference, positive toward
        the scope, mm; NaN invalid.
        sigma_mm: (n,) 1-σ of each height, mm (including the reference points' noise and the
            calibration term).
        sigma_noise_mm: (n,) the part of ``sigma_mm`` from the pixels' noise alone.
    """

    pixels: npt.NDArray[np.int64]
    distance_mm: F64
    height_mm: F64
    sigma_mm: F64
    sigma_noise_mm: F64 | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"pixels": self.pixels.tolist(), "distance_mm": [_j(x) for x in self.distance_mm],
                "height_mm": [_j(x) for x in self.height_mm],
                "sigma_mm": [_j(x) for x in self.sigma_mm]}


@dataclass(frozen=True)
class Measurement:
    """A measurement with its 1-σ uncertainty.

    Attributes:
        kind: one of :data:`KINDS`.
        value_mm: the value (mm; area in mm²). ``profile``: the height farthest from the
            reference (signed). ``depth``: signed, positive toward the scope.
        sigma_mm: 1-σ of ``value_mm`` (mm; mm² for area), NaN if σ is unknown.
        points: the picked points, in the order given (a profile's reference points last).
        profile: the samples (``profile`` only).
        extra: kind-specific figures (e.g. the area's raw value and roughness correction).
    """

    kind: str
    value_mm: float
    sigma_mm: float
    points: list[PickedPoint]
    profile: ProfileSamples | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind, "value_mm": _j(self.value_mm),
                               "sigma_mm": _j(self.sigma_mm),
                               "unit": "mm2" if self.kind == "area" else "mm",
                               "points": [p.to_dict() for p in self.points],
                               "snapped": any(p.snapped for p in self.points), "extra": self.extra}
        if self.profile is not None:
            out["profile"] = self.profile.to_dict()
        return out


def _j(x: float) -> float | None:
    """JSON has no NaN: undefined figures are None."""
    x = float(x)
    return x if math.isfinite(x) else None


# -- inputs ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Surface:
    """The result's arrays as given (no whole-image copies: a click must answer in milliseconds)."""

    points: npt.NDArray[Any]  # (H, W, 3)
    valid: npt.NDArray[np.bool_]
    sigma: npt.NDArray[Any] | None  # (H, W) or None (unknown)
    normal: F64  # (3,) reference-plane normal (noise direction X/(n·X))
    reason: npt.NDArray[Any] | None
    cal_sigma: float = 0.0  # per-point calibration height uncertainty, mm
    cal_length: float = 0.0  # its correlation length, mm (0: independent between points)
    calibration: Calibration | None = None  # its own error model (replaces the two above)

    @property
    def has_cal(self) -> bool:
        return self.calibration is not None or self.cal_sigma > 0

    def cal_rows(self, x: F64) -> F64:
        """(K, n) the calibration's height errors at points ``x`` (n, 3) (their Gram matrix is the
        covariance); 0 rows without a calibration; NaN points contribute nothing."""
        assert self.calibration is not None
        d = self.calibration.height_deviations(x)
        return np.asarray(np.where(np.isfinite(d), d, 0.0), np.float64)

    def cal_point_rows(self, x: F64) -> F64:
        """(K, n, 3) the calibration's 3-D errors of points ``x`` (n, 3)
        (:meth:`Calibration.point_deviations`); NaN points contribute nothing."""
        assert self.calibration is not None
        d = self.calibration.point_deviations(x)
        return np.asarray(np.where(np.isfinite(d), d, 0.0), np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.valid.shape[0]), int(self.valid.shape[1]))

    def ok(self, rows: Any, cols: Any) -> npt.NDArray[np.bool_]:
        """Valid with a finite point, at ``[rows, cols]`` (indices or slices)."""
        finite = np.all(np.isfinite(self.points[rows, cols]), axis=-1)
        return np.asarray(self.valid[rows, cols] & finite)

    def pts(self, rows: Any, cols: Any) -> F64:
        return np.asarray(self.points[rows, cols], np.float64)

    def sig(self, rows: Any, cols: Any) -> F64:
        """σ at ``[rows, cols]``, mm (NaN where unknown: it propagates into the result's σ)."""
        if self.sigma is None:
            return np.full(np.shape(self.valid[rows, cols]), np.nan)
        return np.asarray(self.sigma[rows, cols], np.float64)


def _surface(points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
             plane_normal: npt.ArrayLike | None, reason: npt.ArrayLike | None,
             cal_sigma: float = 0.0, cal_length: float = 0.0,
             calibration: Calibration | None = None) -> _Surface:
    pts = np.asarray(points)
    if pts.ndim != 3 or pts.shape[2] != 3 or not np.issubdtype(pts.dtype, np.floating):
        raise ValueError(f"points: expected a float (H, W, 3) array, got {pts.dtype} {pts.shape}")
    ok = np.asarray(valid)
    if ok.shape != pts.shape[:2] or ok.dtype != np.bool_:
        raise ValueError(f"valid: need a bool array of shape {pts.shape[:2]}, "
                         f"got {ok.dtype} {ok.shape}")
    sig = None if sigma is None else np.asarray(sigma)
    if sig is not None and sig.shape != ok.shape:
        raise ValueError(f"sigma: shape {sig.shape} does not match points {pts.shape[:2]}")
    n = (np.array([0.0, 0.0, 1.0]) if plane_normal is None
         else np.asarray(plane_normal, np.float64).ravel())
    if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
        raise ValueError(f"plane_normal: need 3 finite values, not all zero, got {n!r}")
    r = None if reason is None else np.asarray(reason)
    if r is not None and r.shape != ok.shape:
        raise ValueError(f"reason: shape {r.shape} does not match points {pts.shape[:2]}")
    if not (math.isfinite(cal_sigma) and cal_sigma >= 0):
        raise ValueError(f"calibration_sigma_mm: need a finite value >= 0, got {cal_sigma}")
    if not (math.isfinite(cal_length) and cal_length >= 0):
        raise ValueError(f"calibration_length_mm: need a finite value >= 0, got {cal_length}")
    if calibration is not None and not isinstance(calibration, Calibration):
        raise ValueError("calibration: expected a Calibration")
    if calibration is not None and len(calibration.model.jackknife) < 3:
        calibration = None  # a file without the model's own uncertainty: the two terms above
    return _Surface(pts, ok, sig, n / np.linalg.norm(n), r, float(cal_sigma), float(cal_length),
                    calibration)


def _pixels(pixels: Sequence[Sequence[float]] | npt.ArrayLike, what: str = "points") -> F64:
    px = np.asarray(pixels, np.float64)
    if px.ndim != 2 or px.shape[1] != 2:
        raise ValueError(f"{what}: expected a list of (u, v) pixel coordinates, got shape "
                         f"{px.shape}")
    for i, (u, v) in enumerate(px):
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ValueError(f"{what}: point {i + 1} ({u}, {v}) is not finite")
    return px


def _why(surf: _Surface, u: int, v: int) -> str:
    if surf.reason is not None and int(surf.reason[v, u]) != 0:
        from app.core.reasons import Reason

        try:
            return f"invalid pixel ({Reason(int(surf.reason[v, u])).name})"
        except ValueError:
            pass
    return "invalid pixel"


def pick(surf: _Surface, u: float, v: float, snap_px: float, label: str,
         fill: bool = False) -> PickedPoint:
    """The valid pixel for a click at (u, v), snapping within ``snap_px`` (ValueError naming
    ``label``).

    ``fill``: a click in a hole with no valid pixel within ``snap_px`` is filled from the valid
    points around it (:func:`_linear_fill`) when they make at least :data:`MIN_COVERAGE` of
    the fit's window; else it is refused.
    """
    h, w = surf.shape
    if not (-0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5):
        raise ValueError(f"{label} ({u:g}, {v:g}): outside the {w}x{h} image")
    iu, iv = int(round(u)), int(round(v))
    if surf.ok(iv, iu):
        pu, pv, dist = iu, iv, 0.0
    else:
        r = int(math.floor(snap_px))
        u0, u1, v0, v1 = max(0, iu - r), min(w, iu + r + 1), max(0, iv - r), min(h, iv + r + 1)
        vv, uu = np.nonzero(surf.ok(slice(v0, v1), slice(u0, u1)))
        d2 = (uu + u0 - iu) ** 2 + (vv + v0 - iv) ** 2
        near = d2 <= snap_px**2
        if (r < 1 or not np.any(near)) and fill:
            return _filled_pick(surf, u, v, iu, iv, label)
        if r < 1 or not np.any(near):
            raise ValueError(f"{label} ({u:g}, {v:g}): {_why(surf, iu, iv)} and no valid pixel "
                             f"within {snap_px:g} px")
        k = int(np.flatnonzero(near)[np.argmin(d2[near])])
        pu, pv, dist = int(uu[k] + u0), int(vv[k] + v0), float(math.sqrt(d2[k]))
    x = surf.pts(pv, pu)
    return PickedPoint((float(u), float(v)), (pu, pv), (float(x[0]), float(x[1]), float(x[2])),
                       float(surf.sig(pv, pu)), dist > 0, dist)


def _filled_pick(surf: _Surface, u: float, v: float, iu: int, iv: int, label: str) -> PickedPoint:
    h, w = surf.shape
    r = 68  # the fit's largest window (64 px) and a margin
    r0, c0 = max(0, iv - r), max(0, iu - r)
    ok = surf.ok(slice(r0, min(h, iv + r + 1)), slice(c0, min(w, iu + r + 1)))
    try:
        rows, cols, weights, coverage = _linear_fill(ok, iu - c0, iv - r0, 2)
    except ValueError:
        coverage = 0.0
    if coverage < MIN_COVERAGE:
        raise ValueError(f"{label} ({u:g}, {v:g}): {_why(surf, iu, iv)} in a hole whose "
                         f"surroundings are {100 * coverage:.0f} % valid (a filled point needs "
                         f"{100 * MIN_COVERAGE:.0f} %)")
    rows, cols = rows + r0, cols + c0
    x = weights @ surf.pts(rows, cols)
    sig = float(np.sqrt(np.sum((weights * surf.sig(rows, cols)) ** 2)))
    return PickedPoint((float(u), float(v)), (iu, iv), (float(x[0]), float(x[1]), float(x[2])), sig,
                       False, 0.0, True, coverage)


def _direction(surf: _Surface, x: F64) -> F64:
    """Displacement of point(s) ``x`` (..., 3) per unit height change: X / (n·X)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(x / (x @ surf.normal)[..., None], np.float64)


def _propagate(f: Callable[[F64], float], pts: F64, dirs: F64, sig: F64,
               ids: Sequence[Any]) -> float:
    """1-σ of f(points) for independent height noise per distinct pixel id (first
    order, central differences)."""
    grads: dict[Any, float] = {}
    scale = max(1e-6, float(np.max(np.abs(pts))) * 1e-7)
    for i in range(len(pts)):
        step = scale * 10.0
        p1, p2 = pts.copy(), pts.copy()
        p1[i] += step * dirs[i]
        p2[i] -= step * dirs[i]
        g = (f(p1) - f(p2)) / (2 * step)
        grads[ids[i]] = grads.get(ids[i], 0.0) + g * sig[i]
    return float(math.sqrt(sum(g * g for g in grads.values())))


def _slope(f: Callable[[F64], float], pts: F64, dirs: F64, i: int) -> float:
    """∂f/∂(height of point i), central differences (the step as :func:`_propagate`)."""
    step = max(1e-6, float(np.max(np.abs(pts))) * 1e-7) * 10.0
    p1, p2 = pts.copy(), pts.copy()
    p1[i] += step * dirs[i]
    p2[i] -= step * dirs[i]
    return (f(p1) - f(p2)) / (2 * step)


def _gradient(f: Callable[[F64], float], pts: F64) -> F64:
    """(n, 3) ∂f/∂(x, y, z) of every point of ``pts`` (n, 3), mm (central differences, the step
    as :func:`_propagate`)."""
    step = max(1e-6, float(np.max(np.abs(pts))) * 1e-7) * 10.0
    grad = np.zeros(pts.shape, np.float64)
    for i in range(len(pts)):
        for c in range(3):
            p1, p2 = pts.copy(), pts.copy()
            p1[i, c] += step
            p2[i, c] -= step
            grad[i, c] = (f(p1) - f(p2)) / (2 * step)
    return grad


def _picks(surf: _Surface, pixels: F64, snap_px: float, first: int = 1,
           fill: bool = False) -> list[PickedPoint]:
    return [pick(surf, float(u), float(v), snap_px, f"point {first + i}", fill)
            for i, (u, v) in enumerate(pixels)]


def _outline(surf: _Surface, pixels: F64, snap_px: float, first: int = 1) -> list[PickedPoint]:
    """Vertices that only place a polygon or polyline in the image: snapped to a valid pixel
    when one is near, else kept where clicked (point NaN) — a hole under a vertex is no error."""
    out = []
    for i, (u, v) in enumerate(pixels):
        try:
            out.append(pick(surf, float(u), float(v), snap_px, f"point {first + i}"))
        except ValueError as exc:
            if "outside" in str(exc):
                raise
            nan = float("nan")
            out.append(PickedPoint((float(u), float(v)), (int(round(u)), int(round(v))),
                                   (nan, nan, nan), nan, False, 0.0))
    return out


def _coverage_error(what: str, covered: float) -> ValueError:
    return ValueError(f"points: only {100 * covered:.0f} % of the {what}'s pixels are valid; a "
                      f"measurement needs at least {100 * MIN_COVERAGE:.0f} %")


def _arrays(surf: _Surface,
            picks: list[PickedPoint]) -> tuple[F64, F64, F64, list[tuple[int, int]]]:
    pts = np.array([p.point_mm for p in picks], np.float64)
    sig = np.array([p.sigma_mm for p in picks], np.float64)
    return pts, _direction(surf, pts), sig, [p.pixel for p in picks]


def _correlation(surf: _Surface, a: F64, b: F64) -> F64:
    """Correlation (n, m) of the calibration error between 3-D points ``a`` (n,
    3) and ``b`` (m, 3), mm."""
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = np.linalg.norm(a64[:, None, :] - b64[None, :, :], axis=-1)
    if surf.cal_length <= 0:
        return np.asarray(d == 0, np.float64)
    return np.asarray(np.exp(-d / surf.cal_length), np.float64)


def _cal_sigma(surf: _Surface, coef: F64, x: F64, chunk: int = 1024) -> float:
    """σ of Σ_i coef_i · e_i for the calibration's height errors e_i at points ``x`` (n, 3), mm."""
    coef = np.asarray(coef, np.float64)
    if surf.calibration is not None and len(coef):
        return float(np.linalg.norm(surf.cal_rows(x) @ coef))
    if surf.cal_sigma <= 0 or len(coef) == 0:
        return 0.0
    var = 0.0
    for i in range(0, len(coef), chunk):
        var += float(coef[i:i + chunk] @ _correlation(surf, x[i:i + chunk], x) @ coef)
    return surf.cal_sigma * math.sqrt(max(0.0, var))


def _cal_sigma_3d(surf: _Surface, grad: F64, x: F64) -> float:
    """σ of Σ_i grad_i · e_i for the calibration's 3-D errors e_i of points ``x`` (n, 3), mm
    (``grad`` (n, 3): the value's gradient by each point's position)."""
    return float(np.linalg.norm(np.einsum("knc,nc->k", surf.cal_point_rows(x), grad)))


def _point_measurement(kind: str, f: Callable[[F64], float], pts: F64, dirs: F64, sig: F64,
                       ids: Sequence[Any], picks: list[PickedPoint], surf: _Surface) -> Measurement:
    """The value, its σ from the pixels' noise and, in quadrature, from the calibration term:
    with the calibration's own error model its 3-D point errors (height and sideways, shared
    between the points as the calibration shares them), f followed to first order."""
    noise = _propagate(f, pts, dirs, sig, ids)
    if surf.calibration is not None:
        cal = _cal_sigma_3d(surf, _gradient(f, pts), pts)
    elif surf.has_cal:
        cal = _cal_sigma(surf, np.array([_slope(f, pts, dirs, i) for i in range(len(pts))]), pts)
    else:  # no calibration term: no slopes to evaluate
        cal = 0.0
    return Measurement(kind, f(pts), math.hypot(noise, cal), picks,
                       extra={"sigma_noise_mm": noise, "sigma_calibration_mm": cal,
                              "coverage": min(p.coverage for p in picks)})


def _count(kind: str, px: F64) -> None:
    need = MIN_POINTS[kind]
    exact = EXACT_POINTS.get(kind)
    if exact is not None and len(px) != exact:
        raise ValueError(f"{kind}: needs exactly {exact} points, got {len(px)}")
    if len(px) < need:
        raise ValueError(f"{kind}: needs at least {need} points, got {len(px)}")


# -- the five measurements -------------------------------------------------------------------------
def length(points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
           pixels: Sequence[Sequence[float]] | npt.ArrayLike, *, snap_px: float = 3.0,
           plane_normal: npt.ArrayLike | None = None, reason: npt.ArrayLike | None = None,
           calibration_sigma_mm: float = 0.0, calibration_length_mm: float = 0.0,
           calibration: Calibration | None = None,
           fill_holes: bool = False) -> Measurement:
    """3-D distance between two clicked pixels.

    Args:
        points: (H, W, 3) camera-frame points, mm, NaN invalid.
        valid: (H, W) bool.
        sigma: (H, W) per-pixel 1-σ height noise, mm (None: σ unknown, reported NaN).
        pixels: two (u, v) pixel coordinates.
        snap_px: an invalid click snaps to the nearest valid pixel within this radius, px.
        plane_normal: (3,) reference-plane normal (the direction height noise is measured
            along); None: the optical axis.
        reason: optional (H, W) uint8 reason codes, to name why a click is invalid.
        calibration_sigma_mm: the calibration's systematic height error per point, mm,
            added in quadrature; ``extra`` splits σ into ``sigma_noise_mm`` and
            ``sigma_calibration_mm``.
        calibration_length_mm: its correlation length, mm: points ``d`` mm apart share it
            with correlation ``exp(-d / calibration_length_mm)``; 0: independent between points.
        fill_holes: a click in a hole too wide to snap across is filled from the valid
            points around it (:func:`pick`); its noise is taken as independent of the other
            point's. ``extra.coverage`` is the smaller of the two points' coverage.

    Returns:
        :class:`Measurement`, value and σ in mm.
    """
    surf = _surface(points, valid, sigma, plane_normal, reason, calibration_sigma_mm,
                    calibration_length_mm, calibration)
    px = _pixels(pixels)
    _count("length", px)
    picks = _picks(surf, px, snap_px, fill=fill_holes)
    if picks[0].pixel == picks[1].pixel:
        raise ValueError(f"point 2 {picks[1].pixel}: same pixel as point 1; a length needs two "
                         "distinct points")
    pts, dirs, sig, ids = _arrays(surf, picks)

    def f(p: F64) -> float:
        return float(np.linalg.norm(p[1] - p[0]))

    return _point_measurement("length", f, pts, dirs, sig, ids, picks, surf)


def point_to_line(points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
                  pixels: Sequence[Sequence[float]] | npt.ArrayLike, *, snap_px: float = 3.0,
                  plane_normal: npt.ArrayLike | None = None, reason: npt.ArrayLike | None = None,
           calibration_sigma_mm: float = 0.0, calibration_length_mm: float = 0.0,
           calibration: Calibration | None = None) -> Measurement:
    """Distance (mm, ≥ 0) of point 1 from the 3-D line through points 2 and 3.

    Arguments as :func:`length`, with three pixels: the point, then two on the line.
    """
    surf = _surface(points, valid, sigma, plane_normal, reason, calibration_sigma_mm,
                    calibration_length_mm, calibration)
    px = _pixels(pixels)
    _count("point_to_line", px)
    picks = _picks(surf, px, snap_px)
    pts, dirs, sig, ids = _arrays(surf, picks)
    if np.linalg.norm(pts[2] - pts[1]) < 1e-6:
        raise ValueError(f"points 2 and 3 {picks[1].pixel}, {picks[2].pixel}: coincide; "
                         "they do not define a line")

    def f(p: F64) -> float:
        d = p[2] - p[1]
        return float(np.linalg.norm(np.cross(p[0] - p[1], d)) / np.linalg.norm(d))

    return _point_measurement("point_to_line", f, pts, dirs, sig, ids, picks, surf)


def _plane_normal(p1: F64, p2: F64, p3: F64) -> F64:
    """Unit normal of the plane through three points, oriented toward the camera (origin)."""
    n = np.cross(p2 - p1, p3 - p1)
    n = n / np.linalg.norm(n)
    return -n if float(n @ p1) > 0 else n


#: a reference triangle with a smaller angle leaves its plane ill-defined: its tilt follows the
#: noise, far beyond what a first-order σ describes (seen on the twin at 1°)
MIN_PLANE_ANGLE_DEG = 5.0


def _check_plane(pts: F64, picks: list[PickedPoint], first: int) -> None:
    names = ", ".join(f"{first + i} {p.pixel}" for i, p in enumerate(picks))
    edges = [pts[(i + 1) % 3] - pts[i] for i in range(3)]
    lengths = [float(np.linalg.norm(e)) for e in edges]
    if min(lengths) < 1e-9:
        raise ValueError(f"points {names}: collinear or coincident; they do not define a plane")
    cosines = [-(edges[i - 1] @ edges[i]) / (lengths[i - 1] * lengths[i]) for i in range(3)]
    angles = [math.degrees(math.acos(float(np.clip(c, -1.0, 1.0)))) for c in cosines]
    if min(angles) < MIN_PLANE_ANGLE_DEG:
        raise ValueError(f"points {names}: collinear or coincident (the triangle's smallest "
                         f"angle is {min(angles):.1f}° < {MIN_PLANE_ANGLE_DEG:g}°); "
                         "they do not define a plane well")


def depth(points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
          pixels: Sequence[Sequence[float]] | npt.ArrayLike, *, snap_px: float = 3.0,
          plane_normal: npt.ArrayLike | None = None, reason: npt.ArrayLike | None = None,
           calibration_sigma_mm: float = 0.0, calibration_length_mm: float = 0.0,
           calibration: Calibration | None = None) -> Measurement:
    """Signed distance (mm) of point 1 from the plane through points 2, 3, 4.

    Positive toward the scope (above the reference, as heights in the depth map); a pit
    below the plane reads negative. Arguments as :func:`length`, with four pixels.
    """
    surf = _surface(points, valid, sigma, plane_normal, reason, calibration_sigma_mm,
                    calibration_length_mm, calibration)
    px = _pixels(pixels)
    _count("depth", px)
    picks = _picks(surf, px, snap_px)
    pts, dirs, sig, ids = _arrays(surf, picks)
    _check_plane(pts[1:], picks[1:], 2)

    def f(p: F64) -> float:
        return float((p[0] - p[1]) @ _plane_normal(p[1], p[2], p[3]))

    return _point_measurement("depth", f, pts, dirs, sig, ids, picks, surf)


#: the most samples a profile takes (a polyline across a 1384 x 1032 image a dozen times)
MAX_PROFILE_SAMPLES = 20_000


def polyline_pixels(vertices: F64) -> npt.NDArray[np.int64]:
    """Every pixel along a polyline (u, v): one sample per pixel step along
    each segment, no repeats."""
    parts = []
    for (u0, v0), (u1, v1) in zip(vertices[:-1], vertices[1:], strict=True):
        n = max(1, int(math.ceil(max(abs(u1 - u0), abs(v1 - v0)))))
        t = np.arange(n + 1) / n
        parts.append(np.column_stack([np.rint(u0 + t * (u1 - u0)), np.rint(v0 + t * (v1 - v0))]))
    px = np.concatenate(parts).astype(np.int64)
    keep = np.ones(len(px), bool)
    keep[1:] = np.any(px[1:] != px[:-1], axis=1)
    return px[keep]


def profile(points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
            pixels: Sequence[Sequence[float]] | npt.ArrayLike, *,
            reference: Sequence[Sequence[float]] | npt.ArrayLike | None = None,
            snap_px: float = 3.0, plane_normal: npt.ArrayLike | None = None,
            reason: npt.ArrayLike | None = None, calibration_sigma_mm: float = 0.0,
            calibration_length_mm: float = 0.0, calibration: Calibration | None = None,
            fill_holes: bool = False) -> Measurement:
    """Heights along a polyline, every pixel, against its chord or a 3-point reference plane.

    Without ``reference`` the heights are distances from the 3-D chord between the
    polyline's first and last points, measured in the plane of the chord and the viewing
    direction (positive toward the scope); ``distance_mm`` runs along the chord. With
    ``reference`` (three pixels) they are signed distances from that plane (positive toward
    the scope) and ``distance_mm`` is the 3-D path length along the valid samples.

    Invalid pixels along the way are NaN in the samples (a gap), not snapped; the chord's
    ends and the reference points are picked (snapped; with ``fill_holes``, filled in a
    wider hole) like other clicks, the other vertices only place the line (snapped when a
    valid pixel is near, else kept). ``extra.coverage`` is the valid share of the samples;
    below :data:`MIN_COVERAGE` the profile is refused.
    ``value_mm`` is the height of the sample farthest from the reference, its ``sigma_mm``
    that sample's σ (the σ of a single height, not of a maximum over noisy samples).

    Args:
        pixels: the polyline's vertices, ≥ 2 (u, v).
        reference: None, or three (u, v) pixels spanning the reference plane.
        others: as :func:`length`.
    """
    surf = _surface(points, valid, sigma, plane_normal, reason, calibration_sigma_mm,
                    calibration_length_mm, calibration)
    px = _pixels(pixels)
    _count("profile", px)
    ref_picks: list[PickedPoint] = []
    if reference is not None:
        picks = _outline(surf, px, snap_px)
        rp = _pixels(reference, "reference")
        if len(rp) != 3:
            raise ValueError(f"reference: needs exactly 3 points for a plane, got {len(rp)}")
        ref_picks = _picks(surf, rp, snap_px, first=len(px) + 1, fill=fill_holes)
    else:  # the chord's ends carry the reference; the vertices between only place the line
        first = pick(surf, float(px[0, 0]), float(px[0, 1]), snap_px, "point 1", fill_holes)
        last = pick(surf, float(px[-1, 0]), float(px[-1, 1]), snap_px, f"point {len(px)}",
                    fill_holes)
        picks = [first, *_outline(surf, px[1:-1], snap_px, first=2), last]
    verts = np.array([p.pixel for p in picks], np.float64)
    steps = np.abs(np.diff(verts, axis=0)).max(axis=1).sum()
    if steps > MAX_PROFILE_SAMPLES:
        raise ValueError(f"points: the polyline is {steps:.0f} px long; a profile takes at most "
                         f"{MAX_PROFILE_SAMPLES} samples")
    samples = polyline_pixels(verts)
    if len(samples) < 2:
        raise ValueError("points: the polyline's vertices are all the same pixel")
    su, sv = samples[:, 0], samples[:, 1]
    ok = surf.ok(sv, su)
    sp = surf.pts(sv, su)
    ssig = surf.sig(sv, su)
    sdir = _direction(surf, np.where(ok[:, None], sp, 0.0))
    if reference is None:
        ref_list = [picks[0], picks[-1]]
        rpts, rdir, rsig, rids = _arrays(surf, ref_list)
        if np.linalg.norm(rpts[1] - rpts[0]) < 1e-6:
            raise ValueError(f"points 1 and {len(px)}: the chord's ends coincide")

        def heights(p: F64, r: F64) -> tuple[F64, F64]:
            a, b = r[0], r[1]
            c = (b - a) / np.linalg.norm(b - a)
            view = -(a + b) / 2.0  # toward the camera from the chord's middle
            up = view - (view @ c) * c
            up = up / np.linalg.norm(up)
            return (p - a) @ up, (p - a) @ c
    else:
        rpts, rdir, rsig, rids = _arrays(surf, ref_picks)
        _check_plane(rpts, ref_picks, len(px) + 1)

        def heights(p: F64, r: F64) -> tuple[F64, F64]:
            n = _plane_normal(r[0], r[1], r[2])
            return (p - r[0]) @ n, np.zeros(len(p))

    h, dist = heights(sp, rpts)
    if reference is not None:  # path length along the valid samples
        step = np.zeros(len(sp))
        good = np.flatnonzero(ok)
        if len(good) > 1:
            step[good[1:]] = np.linalg.norm(np.diff(sp[good], axis=0), axis=1)
        dist = np.cumsum(step)
    # first-order σ per sample: its own pixel plus the reference points (merged
    # where they are the same pixel)
    eps = max(1e-6, float(np.nanmax(np.abs(sp[ok]))) * 1e-6) if ok.any() else 1e-6
    g_self = (heights(sp + eps * sdir, rpts)[0] - heights(sp - eps * sdir, rpts)[0]) / (2 * eps)
    g_ref = []
    for j in range(len(rpts)):
        r1, r2 = rpts.copy(), rpts.copy()
        r1[j] += eps * rdir[j]
        r2[j] -= eps * rdir[j]
        g_ref.append((heights(sp, r1)[0] - heights(sp, r2)[0]) / (2 * eps))

    def variance(self_sig: F64, ref_sig: F64) -> F64:
        own = g_self * self_sig
        var = np.zeros(len(sp))
        for j, (pu, pv) in enumerate(rids):
            same = (su == pu) & (sv == pv)
            g = g_ref[j] * ref_sig[j]
            own = np.where(same, own + g, own)
            var += np.where(same, 0.0, g**2)
        return np.asarray(var + own**2, np.float64)

    var_noise = variance(ssig, rsig)
    var_cal = np.zeros(len(sp))
    if surf.calibration is not None:  # e = g_self·e_s + Σ_r g_r·e_r with e = rows' combination
        comb = g_self[None, :] * surf.cal_rows(np.where(ok[:, None], sp, np.nan)) \
            + np.einsum("rs,kr->ks", np.array(g_ref), surf.cal_rows(rpts))
        var_cal = np.sum(np.where(ok[None, :], comb, 0.0) ** 2, axis=0)
    # Σ over the sample and the reference points of g_a g_b ρ(a, b), times s²
    elif surf.cal_sigma > 0:
        gr = np.array(g_ref)  # (R, S)
        rho_sr = _correlation(surf, np.where(ok[:, None], sp, 0.0), rpts)  # (S, R)
        rho_rr = _correlation(surf, rpts, rpts)  # (R, R)
        var_cal = (g_self**2 + 2.0 * g_self * np.einsum("rs,sr->s", gr, rho_sr)
                   + np.einsum("rs,rq,qs->s", gr, rho_rr, gr)) * surf.cal_sigma**2
        var_cal = np.maximum(var_cal, 0.0)
    s = np.where(ok, np.sqrt(var_noise + var_cal), np.nan)
    s_noise = np.where(ok, np.sqrt(var_noise), np.nan)
    h = np.where(ok, h, np.nan)
    dist = np.where(ok, dist, np.nan)
    if not ok.any():
        raise ValueError("points: no valid pixel along the polyline")
    if ok.mean() < MIN_COVERAGE:
        raise _coverage_error("profile", float(ok.mean()))
    k = int(np.nanargmax(np.abs(h)))
    samples_out = ProfileSamples(samples, dist, h, s, s_noise)
    extra = {"reference": "chord" if reference is None else "plane", "samples": int(len(samples)),
             "valid_samples": int(ok.sum()), "coverage": round(float(ok.mean()), 4),
             "at_pixel": [int(su[k]), int(sv[k])],
             "sigma_noise_mm": float(s_noise[k]),
             "sigma_calibration_mm": float(np.sqrt(var_cal[k]))}
    return Measurement("profile", float(h[k]), float(s[k]), picks + ref_picks, samples_out, extra)


# -- area ------------------------------------------------------------------------------------------
def _inside(poly: F64, u: F64, v: F64) -> npt.NDArray[np.bool_]:
    """Even-odd point-in-polygon test, vectorised over the query points."""
    inside = np.zeros(u.shape, bool)
    x1, y1 = poly[-1]
    for x2, y2 in poly:
        crosses = (y1 > v) != (y2 > v)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x1 + (v - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (u < xc)
        x1, y1 = x2, y2
    return inside


def _edge_distance(poly: F64, u: F64, v: F64) -> F64:
    """Distance (px) of each query point from the polygon's boundary."""
    best = np.full(u.shape, np.inf)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        d = b - a
        t = np.clip(((u - a[0]) * d[0] + (v - a[1]) * d[1]) / max(float(d @ d), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.hypot(u - a[0] - t * d[0], v - a[1] - t * d[1]))
    return best


def _segments_cross(a: F64, b: F64, c: F64, d: F64) -> bool:
    def orient(p: F64, q: F64, r: F64) -> float:
        return float((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))

    return (orient(a, b, c) * orient(a, b, d) < 0) and (orient(c, d, a) * orient(c, d, b) < 0)


def area(points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
         pixels: Sequence[Sequence[float]] | npt.ArrayLike, *, window_px: int = 5,
         snap_px: float = 3.0, plane_normal: npt.ArrayLike | None = None,
         reason: npt.ArrayLike | None = None,
           calibration_sigma_mm: float = 0.0, calibration_length_mm: float = 0.0,
           calibration: Calibration | None = None) -> Measurement:
    """Area (mm²) of a polygon drawn on the image, measured on the surface (not its projection).

    The surface, smoothed by a ``window_px`` box mean of the valid points, is sampled on a
    grid inside the polygon and along its edges (step ``window_px``, coarser for polygons of
    more than ~4000 steps² so that a click answers in milliseconds), the
    samples are triangulated (Delaunay in the image, triangles outside a concave polygon
    dropped) and the 3-D triangle areas summed. σ is the first-order propagation of every
    pixel's height noise; the expected area inflation from the smoothed surface's residual
    roughness is subtracted (``extra.roughness_correction_mm2``).

    Holes (invalid pixels) are measured through: a sample with no valid pixel in its box is
    the value at its pixel of a plane fitted to the valid points around it
    (:func:`_linear_fill`; ``extra.samples_filled``), whose noise enters σ through the fit's
    weights; σ does not include the surface's departure from that plane across the hole.
    ``extra.coverage`` is the valid share of the polygon's pixels; below
    :data:`MIN_COVERAGE` the area is refused.

    Args:
        pixels: the polygon's vertices, ≥ 3 (u, v), not self-intersecting; they stay where
            they were clicked (``snap_px`` is not used: a vertex in a hole is filled).
        window_px: smoothing box and sampling step, px (odd, ≥ 1).
        others: as :func:`length`.
    """
    surf = _surface(points, valid, sigma, plane_normal, reason, calibration_sigma_mm,
                    calibration_length_mm, calibration)
    px = _pixels(pixels)
    _count("area", px)
    if not (isinstance(window_px, int | np.integer) and window_px >= 1 and window_px % 2 == 1):
        raise ValueError(f"window_px: need an odd integer >= 1, got {window_px!r}")
    # the vertices as clicked, sub-pixel, never snapped: the surface under one in a hole is filled
    picks = _outline(surf, px, 0.0)
    poly = np.array([p.requested for p in picks], np.float64)
    m = len(poly)
    for i in range(m):
        for j in range(i + 1, m):
            if j == i + 1 or (i == 0 and j == m - 1):
                continue
            if _segments_cross(poly[i], poly[(i + 1) % m], poly[j], poly[(j + 1) % m]):
                raise ValueError(f"points: the polygon's edges {i + 1}-{(i + 1) % m + 1} and "
                                 f"{j + 1}-{(j + 1) % m + 1} cross")
    signed = 0.5 * float(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1)
                                - np.roll(poly[:, 0], -1) * poly[:, 1]))
    if abs(signed) < 1.0:
        raise ValueError("points: the polygon encloses less than one pixel (collinear or "
                         "coincident vertices)")
    h, w = surf.shape
    half = window_px // 2
    u_lo, v_lo = int(poly[:, 0].min()) - half - 1, int(poly[:, 1].min()) - half - 1
    u_hi = int(math.ceil(poly[:, 0].max())) + half + 2
    v_hi = int(math.ceil(poly[:, 1].max())) + half + 2
    bu0, bv0, bu1, bv1 = max(0, u_lo), max(0, v_lo), min(w, u_hi), min(h, v_hi)
    # box means over the bounding box (+ margin): sums via an integral image
    okb = surf.ok(slice(bv0, bv1), slice(bu0, bu1))
    # coverage: the valid share of the pixels whose centres lie inside the polygon
    pu_grid, pv_grid = np.meshgrid(np.arange(bu0, bu1, dtype=np.float64),
                                   np.arange(bv0, bv1, dtype=np.float64))
    in_poly = _inside(poly, pu_grid, pv_grid)
    coverage = float(okb[in_poly].mean()) if in_poly.any() else 0.0
    if coverage < MIN_COVERAGE:
        raise _coverage_error("polygon", coverage)
    pb = np.where(okb[..., None], surf.pts(slice(bv0, bv1), slice(bu0, bu1)), 0.0)
    cnt = _box_sum(okb.astype(np.float64), half)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = _box_sum(pb, half) / cnt[..., None]
    # samples: interior grid + edges, at most ~4000 inside (a large polygon
    # is sampled more coarsely)
    step = max(float(window_px), math.sqrt(abs(signed) / 4000.0))
    gu = np.arange(math.ceil(poly[:, 0].min() / step) * step, poly[:, 0].max() + 1e-9, step)
    gv = np.arange(math.ceil(poly[:, 1].min() / step) * step, poly[:, 1].max() + 1e-9, step)
    grid_u, grid_v = np.meshgrid(gu, gv)
    uu, vv = grid_u.ravel(), grid_v.ravel()
    keep = _inside(poly, uu, vv)
    edge: list[tuple[float, float]] = []
    for i in range(m):
        a, b = poly[i], poly[(i + 1) % m]
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        for t in np.arange(n) / n:
            edge.append((float(a[0] + t * (b[0] - a[0])), float(a[1] + t * (b[1] - a[1]))))
    e = np.array(edge)
    # interior samples too close to the edge make slivers: drop those
    # within step/2 of an edge sample
    su, sv = uu[keep], vv[keep]
    far = _edge_distance(poly, su, sv) > 0.5 * step
    su, sv = su[far], sv[far]
    su = np.concatenate([e[:, 0], su])
    sv = np.concatenate([e[:, 1], sv])
    # bilinear sampling of the smoothed surface; the weight of every pixel in every sample
    lu, lv = su - bu0, sv - bv0
    iu0 = np.clip(np.floor(lu).astype(int), 0, bu1 - bu0 - 2)
    iv0 = np.clip(np.floor(lv).astype(int), 0, bv1 - bv0 - 2)
    fu, fv = lu - iu0, lv - iv0
    # a sample in a hole (no valid pixel in a box it needs) is filled by a local linear fit of the
    # valid points around it (its weights carry their noise into σ)
    # (a box mean missing some pixels is off its sample's position too: those are filled as well)
    full = _box_sum(np.ones(okb.shape), half)
    usable = np.ones(len(su), bool)
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        wgt = (fu if du else 1 - fu) * (fv if dv else 1 - fv)
        usable &= ~((wgt > 1e-12) & (cnt[iv0 + dv, iu0 + du] < full[iv0 + dv, iu0 + du] - 0.5))
    fills = {}
    for hole in np.flatnonzero(~usable).tolist():
        try:
            fills[hole] = _linear_fill(okb, su[hole] - bu0, sv[hole] - bv0, window_px)[:3]
        except ValueError:
            raise ValueError(f"points: no valid pixels around ({su[hole]:.0f}, {sv[hole]:.0f}) to "
                             f"fill the polygon's hole (coverage {100 * coverage:.0f} %)") from None
    corners = [(0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv),
               (1, 1, fu * fv)]
    corners = [(du, dv, np.where(usable, wgt, 0.0)) for du, dv, wgt in corners]
    X = np.zeros((len(su), 3))
    for du, dv, wgt in corners:
        X += wgt[:, None] * np.nan_to_num(smooth[iv0 + dv, iu0 + du])
    pts_b = surf.pts(slice(bv0, bv1), slice(bu0, bu1))
    for i, (rows, cols, w_fit) in fills.items():
        X[i] = w_fit @ pts_b[rows, cols]
    # a regular grid is all cocircular quadruples, slow for Qhull: triangulate the samples nudged by
    # 1e-3 px (a valid triangulation of the exact samples too), sample the surface at the exact ones
    nudge = np.random.default_rng(0).uniform(-1e-3, 1e-3, (len(su), 2))
    from scipy.spatial import Delaunay  # deferred: scipy.spatial is not needed to start

    tri = Delaunay(np.column_stack([su, sv]) + nudge)
    simp = tri.simplices
    cu, cv = su[simp].mean(axis=1), sv[simp].mean(axis=1)
    simp = simp[_inside(poly, cu, cv)]
    # slivers of collinear samples (along an edge) cover no image area: their 3-D area is only noise
    e1u, e1v = su[simp[:, 1]] - su[simp[:, 0]], sv[simp[:, 1]] - sv[simp[:, 0]]
    e2u, e2v = su[simp[:, 2]] - su[simp[:, 0]], sv[simp[:, 2]] - sv[simp[:, 0]]
    simp = simp[np.abs(e1u * e2v - e1v * e2u) > 1e-3 * step]
    a_, b_, c_ = X[simp[:, 0]], X[simp[:, 1]], X[simp[:, 2]]
    cross = np.cross(b_ - a_, c_ - a_)
    norm = np.linalg.norm(cross, axis=1)
    raw = 0.5 * float(norm.sum())
    # gradient of the area with respect to each sample's position: ∂A_t/∂a = ½ n̂ × (c − b), cyclic
    with np.errstate(invalid="ignore", divide="ignore"):
        nh = np.where(norm[:, None] > 1e-6 * float(np.median(norm)), cross / norm[:, None], 0.0)
    grad = np.zeros_like(X)
    for k, (p, q) in enumerate(((1, 2), (2, 0), (0, 1))):
        g = 0.5 * np.cross(nh, X[simp[:, q]] - X[simp[:, p]])
        np.add.at(grad, simp[:, k], g)
    dirs = _direction(surf, X)
    coef = np.einsum("ij,ij->i", grad, dirs)  # ∂A/∂(height noise of sample i)
    # spread each sample's coefficient over the pixels of its box means: c_p = Σ_i coef_i w_ip
    cimg = np.zeros(cnt.shape)
    for du, dv, wgt in corners:
        ci, cj = iv0 + dv, iu0 + du
        share = coef * wgt / np.maximum(cnt[ci, cj], 1.0)
        for oy in range(-half, half + 1):
            for ox in range(-half, half + 1):
                y, x = ci + oy, cj + ox
                inb = (y >= 0) & (y < cnt.shape[0]) & (x >= 0) & (x < cnt.shape[1])
                np.add.at(cimg, (y[inb], x[inb]), share[inb])
    for i, (rows, cols, w_fit) in fills.items():
        np.add.at(cimg, (rows, cols), coef[i] * w_fit)
    sig_b = np.where(okb, surf.sig(slice(bv0, bv1), slice(bu0, bu1)), 0.0)
    sigma_a = float(np.sqrt(np.sum((cimg * sig_b * okb) ** 2)))
    # the calibration term: systematic and smooth, so not reduced by the box means; shared between
    # samples (its 3-D rows with the calibration's own model: a focal length's error scales the
    # area; else correlated by distance: a height error shared by the polygon scales its area)
    sigma_cal = _cal_sigma_3d(surf, grad, X) if surf.calibration is not None \
        else _cal_sigma(surf, coef, X)
    # variance of each sample's height noise (box mean, bilinear mix;
    # neighbours' overlap ignored here)
    var_box = _box_sum(np.where(okb, sig_b**2, 0.0), half) / np.maximum(cnt, 1.0) ** 2
    var_s = np.zeros(len(su))
    for du, dv, wgt in corners:
        var_s += wgt**2 * var_box[iv0 + dv, iu0 + du]
    for i, (rows, cols, w_fit) in fills.items():
        var_s[i] = float(np.sum((w_fit * sig_b[rows, cols]) ** 2))
    # roughness inflation: E[ΔA_t] = A_t · E|∇h_n|² / 2, h_n the noise's normal component
    a_vec, b_vec = b_ - a_, c_ - a_
    gmat = np.stack([np.stack([np.einsum("ij,ij->i", a_vec, a_vec),
                               np.einsum("ij,ij->i", a_vec, b_vec)], -1),
                     np.stack([np.einsum("ij,ij->i", a_vec, b_vec),
                               np.einsum("ij,ij->i", b_vec, b_vec)], -1)], -2)
    # (T, 3) normal-component variances
    vn = var_s[simp] * np.einsum("tkj,tj->tk", dirs[simp], nh) ** 2
    cov = np.stack([np.stack([vn[:, 1] + vn[:, 0], vn[:, 0]], -1),
                    np.stack([vn[:, 0], vn[:, 2] + vn[:, 0]], -1)], -2)
    # slivers of collinear edge samples: no area, no roughness
    good = norm > 1e-6 * float(np.median(norm))
    corr = 0.0
    if np.any(good):
        tr = np.einsum("tij,tji->t", np.linalg.inv(gmat[good]), cov[good])
        corr = float(np.sum(0.5 * norm[good] * tr / 2.0))
    known = math.isfinite(corr) and math.isfinite(sigma_a)
    value = raw - (corr if known else 0.0)
    extra = {"raw_mm2": raw, "roughness_correction_mm2": corr if known else None,
             "samples": int(len(su)), "triangles": int(len(simp)), "window_px": int(window_px),
             "step_px": round(step, 3),
             "projected_px2": abs(signed), "coverage": round(coverage, 4),
             "samples_filled": len(fills)}
    extra.update(sigma_noise_mm=sigma_a, sigma_calibration_mm=sigma_cal)
    return Measurement("area", value, math.hypot(sigma_a, sigma_cal), picks, None, extra)


def _linear_fill(ok: npt.NDArray[np.bool_], u: float, v: float, window_px: int,
                 min_pixels: int = 30
                 ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], F64, float]:
    """Weights predicting a point at (u, v) (px, in ``ok``'s frame) from the valid pixels around it.

    The smallest square window (half-width 2·window_px, doubling, at most 64 px) whose valid
    pixels number at least ``min_pixels`` gives a least-squares quadratic surface
    X = a + b·du + c·dv + d·du² + e·du·dv + f·dv² per coordinate (du = u' − u, dv = v' − v;
    a plane if the quadratic is ill-conditioned there); the prediction is ``a``, a weighted
    sum of those pixels' points. Returns (rows, cols, weights (n,) summing to 1, the valid
    share of the window's pixels). ``ValueError`` if no window will do.
    """
    h, w = ok.shape
    r = 2 * window_px
    while r <= 64:
        r0, r1 = max(0, int(v) - r), min(h, int(v) + r + 2)
        c0, c1 = max(0, int(u) - r), min(w, int(u) + r + 2)
        rows, cols = np.nonzero(ok[r0:r1, c0:c1])
        if len(rows) >= min_pixels:
            rows, cols = rows + r0, cols + c0
            du, dv = (cols - u) / r, (rows - v) / r  # scaled: a well-conditioned design
            for a in (np.column_stack([np.ones(len(rows)), du, dv, du * du, du * dv, dv * dv]),
                      np.column_stack([np.ones(len(rows)), du, dv])):
                gram = a.T @ a
                if np.linalg.cond(gram) < 1e6:
                    # the first row of (AᵀA)⁻¹Aᵀ: the fitted value at (u, v)
                    weights = np.linalg.solve(gram, a.T)[0]
                    coverage = len(rows) / float((r1 - r0) * (c1 - c0))
                    return rows, cols, np.asarray(weights, np.float64), coverage
        r *= 2
    raise ValueError(f"(u, v) = ({u:.0f}, {v:.0f}): no window of at most 64 px holds "
                     f"{min_pixels} valid pixels around it")


def _box_sum(a: F64, half: int) -> F64:
    """Sum over the (2·half+1)² box around each pixel (zero outside the array)."""
    k = 2 * half + 1
    return np.asarray(cv2.boxFilter(np.ascontiguousarray(a, np.float64), -1, (k, k),
                                    normalize=False, borderType=cv2.BORDER_CONSTANT), np.float64)


# -- dispatch --------------------------------------------------------------------------------------
Kind = Literal["length", "point_to_line", "depth", "profile", "area"]


def measure(kind: str, points: npt.ArrayLike, valid: npt.ArrayLike, sigma: npt.ArrayLike | None,
            pixels: Sequence[Sequence[float]] | npt.ArrayLike, *,
            reference: Sequence[Sequence[float]] | npt.ArrayLike | None = None,
            snap_px: float = 3.0, plane_normal: npt.ArrayLike | None = None,
            reason: npt.ArrayLike | None = None, calibration_sigma_mm: float = 0.0,
            calibration_length_mm: float = 0.0, calibration: Calibration | None = None,
            fill_holes: bool = False) -> Measurement:
    """One measurement of ``kind`` (see :data:`KINDS`); ``reference`` only for ``profile``.

    ``fill_holes`` (length, profile): a click in a hole too wide to snap across is filled
    from the valid points around it (see :func:`pick`); an area always measures through holes.
    """
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    if not (math.isfinite(snap_px) and snap_px >= 0):
        raise ValueError(f"snap_px: need a finite value >= 0, got {snap_px}")
    if reference is not None and kind != "profile":
        raise ValueError(f"reference: only a profile takes reference points, not {kind}")
    kw: dict[str, Any] = {"snap_px": snap_px, "plane_normal": plane_normal, "reason": reason,
                          "calibration_sigma_mm": calibration_sigma_mm,
                          "calibration_length_mm": calibration_length_mm,
                          "calibration": calibration}
    if kind == "profile":
        return profile(points, valid, sigma, pixels, reference=reference, fill_holes=fill_holes,
                       **kw)
    if kind == "length":
        return length(points, valid, sigma, pixels, fill_holes=fill_holes, **kw)
    fn = {"point_to_line": point_to_line, "depth": depth, "area": area}[kind]
    return fn(points, valid, sigma, pixels, **kw)
