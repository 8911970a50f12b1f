"""Camera calibration with the lens-distortion model chosen on held-out data, and the field it
supports.

A bench board often covers only the centre of the field. OpenCV's polynomial distortion is then
fitted from points out to some normalised radius ``r_max`` and extrapolated beyond it; with more
terms than the data determine (k2, k3, tangential) the extrapolation diverges fast (pixels of
error at the image corners while the in-sample reprojection error stays at 0.06 px). So:

1. Hold out by radius: the board corners beyond ``SPLIT·r_max`` (normalised, from the distortion
   centre) are left out, every candidate model (:data:`CANDIDATE_MODELS`, fewest terms first, and
   :data:`REDUCED_MODEL`) is fitted to the inner ones and judged by its reprojection error on the
   outer ones — the same extrapolation, by the factor ``1/SPLIT``, the calibration will need
   beyond its data.
2. The simplest candidate within :data:`TIE` (or :data:`TIE_PX`) of the best held-out error is
   refitted to all corners — k1 alone only when its held-out error is no larger than theirs:
   dropping a real k2 (a near tie) biases every ray beyond the boards, while fitting a k2 that
   is 0 only widens the uncertainty the calibration's leave-one-pose-out refits measure.
3. The corner-verified field is the ellipse of normalised radius ``r_max`` — extended by the
   factor the held-out test verified (``1/SPLIT``) when the chosen model's held-out error stayed
   within :data:`EXTRAPOLATION_TOLERANCE` of its in-sample error on the same points; else
   ``r_max``. The lens model is *defined* farther, to :func:`defined_radius`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

_NO_TANGENT = cv2.CALIB_ZERO_TANGENT_DIST
#: candidate distortion models, fewest free terms first (OpenCV flags)
DISTORTION_MODELS: dict[str, int] = {
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | _NO_TANGENT,
    "k1,k2": cv2.CALIB_FIX_K3 | _NO_TANGENT,
    "k1,p1,p2": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3,
    "k1,k2,p1,p2": cv2.CALIB_FIX_K3,
    "k1,k2,k3,p1,p2": 0,
}
#: the free coefficients of each model, as indices into OpenCV's (k1, k2, p1, p2, k3)
DISTORTION_TERMS: dict[str, tuple[int, ...]] = {
    "k1": (0,),
    "k1,k2": (0, 1),
    "k1,p1,p2": (0, 2, 3),
    "k1,k2,p1,p2": (0, 1, 2, 3),
    "k1,k2,k3,p1,p2": (0, 1, 2, 3, 4),
}
#: the models the tie rule chooses among, all with k2 (a real k2 only 1–2 σ from 0 at the
#: boards' reach still bends the rays beyond them; the calibration's leave-one-pose-out refits
#: carry a fitted term's uncertainty into σ_model, a dropped term's bias they cannot)
CANDIDATE_MODELS = ("k1,k2", "k1,k2,p1,p2", "k1,k2,k3,p1,p2")
#: k1 alone only where the held-out corners do not favour k2: its held-out error is no larger
#: than every candidate's (no preference for the simpler model on a near tie)
REDUCED_MODEL = "k1"
#: every lens model the held-out test weighs, fewest terms first (the calibration refits the
#: next one after its choice: its disagreement is part of sigma_model past the corners)
MODEL_LADDER = (REDUCED_MODEL, *CANDIDATE_MODELS)
#: the lens model is defined (rays do not fold over) while d r_d / d r >= this
MIN_RADIAL_SLOPE = 0.2
SPLIT = 0.75  # corners beyond SPLIT·r_max are held out
TIE = 1.10  # a simpler model within 10 % of the best held-out error is preferred …
TIE_PX = 0.005  # … or within 0.005 px of it (differences below that are immaterial)
EXTRAPOLATION_TOLERANCE = (
    1.5  # held-out error / in-sample error on the same points that still counts as safe
)
MIN_VIEW_POINTS = 6
_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-12)


@dataclass
class CameraFit:
    """The calibrated camera and how its distortion model was chosen.

    Attributes:
        rms_px: in-sample RMS reprojection error, px.
        camera_matrix: (3, 3); dist_coeffs: (5,) OpenCV k1, k2, p1, p2, k3.
        rvecs, tvecs: per view (3, 1) board pose.
        model: the chosen entry of :data:`DISTORTION_MODELS`.
        held_out_px: per candidate its held-out RMS reprojection error on the outer corners, px
            (NaN when it could not be fitted on the inner ones).
        r_max: largest normalised radius of a board corner; field_radius: the supported radius.
    """

    rms_px: float
    camera_matrix: F64
    dist_coeffs: F64
    rvecs: list[F64]
    tvecs: list[F64]
    model: str
    held_out_px: dict[str, float] = field(default_factory=dict)
    r_max: float = math.inf
    field_radius: float = math.inf

    def field_px(self) -> tuple[float, float, float, float] | None:
        """(cx, cy, rx, ry) of the supported field ellipse, px (None: unbounded)."""
        return self._ellipse(self.field_radius)

    def defined_radius(self) -> float:
        """The distorted normalised radius up to which the lens model is defined: its radial
        polynomial still increases (:data:`MIN_RADIAL_SLOPE`); inf when it does to r = 3."""
        return defined_radius(self.dist_coeffs)

    def defined_field_px(self) -> tuple[float, float, float, float] | None:
        """(cx, cy, rx, ry) of the ellipse where the lens model is defined, px (None: all)."""
        return self._ellipse(self.defined_radius())

    def _ellipse(self, radius: float) -> tuple[float, float, float, float] | None:
        if not math.isfinite(radius):
            return None
        k = self.camera_matrix
        return (float(k[0, 2]), float(k[1, 2]), radius * float(k[0, 0]), radius * float(k[1, 1]))

    def summary(self) -> dict[str, object]:
        """JSON-able record for the calibration file."""
        return {"distortion_model": self.model,
                "held_out_px": {k: _num(v) for k, v in self.held_out_px.items()},
                "split": SPLIT, "r_max": _num(self.r_max), "field_radius": _num(self.field_radius),
                "defined_radius": _num(self.defined_radius())}


def defined_radius(dist_coeffs: npt.ArrayLike) -> float:
    """Distorted normalised radius where OpenCV's radial polynomial ``r·(1 + k1 r² + k2 r⁴ +
    k3 r⁶)`` of ``dist_coeffs`` (k1, k2, p1, p2, k3) first has a slope below
    :data:`MIN_RADIAL_SLOPE` (beyond it rays fold over); inf when not before r = 3."""
    d = np.zeros(5)
    dc = np.asarray(dist_coeffs, np.float64).ravel()[:5]
    d[: dc.size] = dc
    k1, k2, k3 = d[0], d[1], d[4]
    r = np.linspace(0.0, 3.0, 3001)
    r2 = r * r
    slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2))
    low = np.flatnonzero(slope < MIN_RADIAL_SLOPE)
    if low.size == 0:
        return math.inf
    rf = r[low[0]]
    return float(rf * (1 + k1 * rf**2 + k2 * rf**4 + k3 * rf**6))


def _num(x: float) -> float | None:
    return round(float(x), 6) if math.isfinite(x) else None


def _calibrate(
    obj: list[npt.NDArray[np.float32]],
    img: list[npt.NDArray[np.float32]],
    image_size: tuple[int, int],
    flags: int,
) -> tuple[float, F64, F64, list[F64], list[F64]]:
    rms, cam, dist, rvecs, tvecs = cv2.calibrateCamera(
        obj, img, image_size, None, None, flags=flags, criteria=_CRITERIA
    )
    return (
        float(rms),
        np.asarray(cam, np.float64),
        np.asarray(dist, np.float64).ravel()[:5],
        [np.asarray(r, np.float64) for r in rvecs],
        [np.asarray(t, np.float64) for t in tvecs],
    )


def calibrate_views(
    obj: list[npt.NDArray[np.float32]],
    img: list[npt.NDArray[np.float32]],
    image_size: tuple[int, int],
    flags: int,
) -> tuple[float, F64, F64, list[F64], list[F64]]:
    """OpenCV's camera calibration of board views with the distortion ``flags`` (one of
    :data:`DISTORTION_MODELS`): (RMS px, camera matrix (3, 3), dist (5,), rvecs, tvecs)."""
    return _calibrate(obj, img, image_size, flags)


def _radii(img: list[npt.NDArray[np.float32]], cam: F64) -> list[F64]:
    return [
        np.hypot(
            (p.reshape(-1, 2)[:, 0] - cam[0, 2]) / cam[0, 0],
            (p.reshape(-1, 2)[:, 1] - cam[1, 2]) / cam[1, 1],
        )
        for p in img
    ]


def _reprojection(
    obj: npt.NDArray[np.float32],
    img: npt.NDArray[np.float32],
    rvec: F64,
    tvec: F64,
    cam: F64,
    dist: F64,
) -> F64:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, cam, dist)
    return np.asarray(np.linalg.norm(proj.reshape(-1, 2) - img.reshape(-1, 2), axis=1), np.float64)


def calibrate_camera(
    obj: list[npt.NDArray[np.float32]],
    img: list[npt.NDArray[np.float32]],
    image_size: tuple[int, int],
    *,
    select: bool = True,
) -> CameraFit:
    """Camera intrinsics and distortion from board views, the distortion model chosen by radial
    hold-out.

    Args:
        obj: per view (n, 3) float32 board points, mm.
        img: per view (n, 1, 2) float32 detected pixel coordinates.
        image_size: (width, height), px.
        select: False keeps OpenCV's k1, k2, p1, p2 (the previous behaviour) with an unbounded
            field.

    Returns:
        :class:`CameraFit`.
    """
    if not select:
        rms, cam, dist, rv, tv = _calibrate(obj, img, image_size, DISTORTION_MODELS["k1,k2,p1,p2"])
        return CameraFit(rms, cam, dist, rv, tv, "k1,k2,p1,p2")
    _, cam0, _, _, _ = _calibrate(obj, img, image_size, DISTORTION_MODELS["k1"])
    radii = _radii(img, cam0)
    r_max = float(max(float(r.max()) for r in radii))
    inner = [r < SPLIT * r_max for r in radii]
    views = [k for k in range(len(obj)) if int(inner[k].sum()) >= MIN_VIEW_POINTS]
    held: dict[str, float] = {}
    in_sample: dict[str, float] = {}
    has_outer = any(int((~inner[k]).sum()) > 0 for k in views)
    for name in MODEL_LADDER:
        flags = DISTORTION_MODELS[name]
        held[name] = math.nan
        if len(views) < 3 or not has_outer:
            continue
        try:
            _, cam, dist, rv, tv = _calibrate(
                [obj[k][inner[k]] for k in views],
                [img[k][inner[k]] for k in views],
                image_size,
                flags,
            )
        except cv2.error:
            continue
        err = np.concatenate(
            [
                _reprojection(obj[k][~inner[k]], img[k][~inner[k]], rv[i], tv[i], cam, dist)
                for i, k in enumerate(views)
                if (~inner[k]).any()
            ]
        )
        held[name] = float(np.sqrt(np.mean(err**2))) if np.all(np.isfinite(err)) else math.nan
    finite = {k: v for k, v in held.items() if math.isfinite(v) and k != REDUCED_MODEL}
    if finite:
        best = min(finite.values())
        chosen = next(k for k, v in finite.items() if v <= max(TIE * best, best + TIE_PX))
        reduced = held[REDUCED_MODEL]
        if math.isfinite(reduced) and reduced <= best:
            chosen = REDUCED_MODEL
            finite[REDUCED_MODEL] = reduced
    else:
        chosen = "k1,k2,p1,p2"
    rms, cam, dist, rv, tv = _calibrate(obj, img, image_size, DISTORTION_MODELS[chosen])
    radius = r_max
    if chosen in finite:
        outer_err = np.concatenate(
            [
                _reprojection(obj[k][~inner[k]], img[k][~inner[k]], rv[k], tv[k], cam, dist)
                for k in views
                if (~inner[k]).any()
            ]
        )
        in_sample[chosen] = float(np.sqrt(np.mean(outer_err**2)))
        if finite[chosen] <= max(EXTRAPOLATION_TOLERANCE * in_sample[chosen], TIE_PX):
            radius = r_max / SPLIT
    return CameraFit(rms, cam, dist, rv, tv, chosen, held, r_max, radius)


def field_shortfall(
    field_px: tuple[float, float, float, float] | None, image_size: tuple[int, int]
) -> dict[str, float]:
    """Per image ninth (``"top left"`` … ``"bottom right"``) the fraction of its pixels outside the
    supported field ellipse; ninths fully inside are left out."""
    if field_px is None:
        return {}
    w, h = image_size
    cx, cy, rx, ry = field_px
    v, u = np.mgrid[0:h:4, 0:w:4]
    out = ((u - cx) / rx) ** 2 + ((v - cy) / ry) ** 2 > 1.0
    names = {}
    for i, rn in enumerate(("top", "middle", "bottom")):
        for j, cn in enumerate(("left", "centre", "right")):
            blk = out[
                (v >= i * h / 3) & (v < (i + 1) * h / 3) & (u >= j * w / 3) & (u < (j + 1) * w / 3)
            ]
            frac = float(blk.mean()) if blk.size else 0.0
            if frac > 0:
                names["centre" if (i, j) == (1, 1) else f"{rn} {cn}"] = frac
    return names
