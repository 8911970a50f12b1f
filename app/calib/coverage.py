"""Calibration coverage: the image × height cells the board poses so far vouch for; the next pose.

The calibrated volume is cut into cells: image columns × rows × height bins above the reference
plane (pose 0). A cell is *covered* when board points of some pose fall in it, and *calibrated*
when it is covered or the depth model's own uncertainty there (σ_model, e.g. the jackknife over
board poses of :meth:`app.core.geometric.GeometricModel.height_sigma`) is within a tolerance.
The share of calibrated cells against a target says when enough poses are taken; the deficit
per image ninth and height bin, and the board tilts seen so far, give the next pose in words.

Pure numerics (numpy and OpenCV); the session (:mod:`app.service.calibration_session`) and
``fringescope calibrate`` call it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from app.core.depth_model import BoardSamples, ReferencePlane
from app.core.geometric import MODEL_SIGMA_TOLERANCE_MM, GeometricModel

F64 = npt.NDArray[np.float64]
#: σ_model (mm) of the model at pixels (n, 2) (u, v) and heights (n,) mm; NaN where undefined
SigmaFn = Callable[[F64, F64], F64]

_ROWS = ("upper", "", "lower")
_COLS = ("left", "", "right")
#: board tilt suggested for a new pose, degrees (the simulator's calibration walk uses ~30°)
SUGGESTED_TILT_DEG = 25.0
#: a pose counts as tilted about an axis beyond this, degrees
TILTED_DEG = 10.0


@dataclass(frozen=True)
class CoverageSpec:
    """The target volume and its cells.

    Attributes:
        cells: (columns, rows) of image cells (multiples of 3 keep the ninths whole).
        height_range_mm: (lo, hi) heights above the reference plane the calibration should span.
        height_bins: height bins over that range.
        target_share: share of calibrated cells at which the volume counts as reached.
        sigma_tolerance_mm: a cell without board points is calibrated when σ_model ≤ this.
        min_poses: poses needed before the target can count as reached.
    """

    cells: tuple[int, int] = (6, 6)
    height_range_mm: tuple[float, float] = (0.0, 20.0)
    height_bins: int = 4
    target_share: float = 0.9
    sigma_tolerance_mm: float = MODEL_SIGMA_TOLERANCE_MM
    min_poses: int = 3

    def __post_init__(self) -> None:
        if min(self.cells) < 1 or self.height_bins < 1:
            raise ValueError(
                f"cells, height_bins: must be positive, got {self.cells}, {self.height_bins}"
            )
        lo, hi = self.height_range_mm
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"height_range_mm: need finite lo < hi, got {self.height_range_mm}")
        if not 0.0 < self.target_share <= 1.0:
            raise ValueError(f"target_share: must be in (0, 1], got {self.target_share}")

    @property
    def height_edges_mm(self) -> F64:
        """(height_bins + 1,) bin edges, mm."""
        return np.linspace(*self.height_range_mm, self.height_bins + 1)


@dataclass(frozen=True)
class PoseGeometry:
    """One board pose seen by the camera.

    Attributes:
        uv: (n, 2) float64 pixels (u, v) of points over the board.
        height_mm: (n,) float64 their heights above the reference plane, mm.
        tilt_vertical_deg: the board's tilt from the reference plane about the image's vertical
            axis, degrees; positive: its right edge nearer the scope.
        tilt_horizontal_deg: about the horizontal axis; positive: its bottom edge nearer the scope.
    """

    uv: F64
    height_mm: F64
    tilt_vertical_deg: float
    tilt_horizontal_deg: float


@dataclass(frozen=True)
class PoseAdvice:
    """The next pose, in numbers and in words.

    Attributes:
        region: the image ninth to move the board's centre to (``"lower-left"``, ``"upper"``,
            ``"centre"`` …).
        u_px, v_px: that ninth's centre, px.
        height_mm: the board centre's height above the reference plane, mm.
        tilt_vertical_deg, tilt_horizontal_deg: the tilts to give it (signs as in
            :class:`PoseGeometry`), degrees.
        text: one line for the user.
    """

    region: str
    u_px: float
    v_px: float
    height_mm: float
    tilt_vertical_deg: float
    tilt_horizontal_deg: float
    text: str


@dataclass(frozen=True)
class CoverageMap:
    """Cells covered by the board poses so far and σ_model per cell.

    Attributes:
        spec: the target volume.
        image_size: (width, height), px.
        points: (bins, rows, cols) int64 board points per cell.
        sigma_mm: (bins, rows, cols) float64 σ_model at the cell's centre pixel and bin-centre
            height, mm (NaN: no model yet, or undefined there).
        poses: poses counted.
    """

    spec: CoverageSpec
    image_size: tuple[int, int]
    points: npt.NDArray[np.int64]
    sigma_mm: F64
    poses: int

    @property
    def covered(self) -> npt.NDArray[np.bool_]:
        """(bins, rows, cols) cells with board points."""
        return np.asarray(self.points > 0)

    @property
    def calibrated(self) -> npt.NDArray[np.bool_]:
        """(bins, rows, cols) cells covered or with σ_model within the tolerance."""
        sig = np.where(np.isfinite(self.sigma_mm), self.sigma_mm, np.inf)
        return np.asarray(self.covered | (sig <= self.spec.sigma_tolerance_mm))

    @property
    def covered_share(self) -> float:
        return float(self.covered.mean())

    @property
    def calibrated_share(self) -> float:
        return float(self.calibrated.mean())

    @property
    def reached(self) -> bool:
        """The calibrated share reaches the target (with enough poses)."""
        return self.poses >= self.spec.min_poses and self.calibrated_share >= self.spec.target_share

    def status_line(self) -> str:
        """One line: the shares against the target."""
        lo, hi = self.spec.height_range_mm
        head = (
            f"coverage: {100 * self.calibrated_share:.0f} % of the image x {lo:g}-{hi:g} mm cells "
            f"calibrated ({100 * self.covered_share:.0f} % with board points), "
            f"target {100 * self.spec.target_share:.0f} %"
        )
        return head + (": reached" if self.reached else ": not yet")

    def table(self) -> str:
        """Per height bin a character map of the cells (``#`` board points, ``+`` σ_model within
        the tolerance, ``.`` neither) and the largest σ_model of the bin."""
        edges = self.spec.height_edges_mm
        lines = [self.status_line()]
        for b in range(self.spec.height_bins):
            sig = self.sigma_mm[b]
            worst = f"{1000 * float(np.nanmax(sig)):.1f} um" if np.isfinite(sig).any() else "-"
            lines.append(
                f"  heights {edges[b]:5.1f}-{edges[b + 1]:5.1f} mm (max sigma_model {worst}):"
            )
            for r in range(self.spec.cells[1]):
                row = "".join(
                    "#" if self.covered[b, r, c] else "+" if self.calibrated[b, r, c] else "."
                    for c in range(self.spec.cells[0])
                )
                lines.append(f"    {row}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: shares, target, the maps as nested lists [bin][row][col] (σ in µm; None:
        undefined)."""
        sig_um = np.round(1000.0 * self.sigma_mm, 3)
        return {
            "cells": list(self.spec.cells),
            "height_edges_mm": [round(float(x), 3) for x in self.spec.height_edges_mm],
            "poses": self.poses,
            "covered": self.covered.astype(int).tolist(),
            "sigma_model_um": [
                [[float(x) if math.isfinite(x) else None for x in row] for row in b]
                for b in sig_um.tolist()
            ],
            "covered_share": round(self.covered_share, 4),
            "calibrated_share": round(self.calibrated_share, 4),
            "target_share": self.spec.target_share,
            "sigma_tolerance_um": 1000.0 * self.spec.sigma_tolerance_mm,
            "reached": self.reached,
        }


def coverage_map(
    poses: Sequence[PoseGeometry],
    image_size: tuple[int, int],
    *,
    sigma: SigmaFn | None = None,
    spec: CoverageSpec | None = None,
) -> CoverageMap:
    """The cells the board ``poses`` cover and σ_model per cell.

    Args:
        poses: the board poses so far (pose 0 the reference plane).
        image_size: (width, height) of the camera, px.
        sigma: σ_model (mm) at pixels (n, 2) and heights (n,) mm, or None (no model yet: NaN).
        spec: the cells and target (default :class:`CoverageSpec`).

    Returns:
        :class:`CoverageMap`; points outside the image or the height range count nowhere.
    """
    spec = spec or CoverageSpec()
    w, h = (int(x) for x in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size: must be positive, got {image_size}")
    gw, gh = spec.cells
    nb = spec.height_bins
    lo, hi = spec.height_range_mm
    points = np.zeros((nb, gh, gw), np.int64)
    for k, p in enumerate(poses):
        uv, z = (
            np.asarray(p.uv, np.float64).reshape(-1, 2),
            np.asarray(p.height_mm, np.float64).ravel(),
        )
        if len(uv) != len(z):
            raise ValueError(f"poses[{k}]: {len(uv)} pixels for {len(z)} heights")
        ok = (
            np.isfinite(z)
            & (z >= lo)
            & (z <= hi)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < w)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < h)
        )
        b = np.minimum(((z[ok] - lo) / (hi - lo) * nb).astype(np.int64), nb - 1)
        r = np.minimum((uv[ok, 1] * gh / h).astype(np.int64), gh - 1)
        c = np.minimum((uv[ok, 0] * gw / w).astype(np.int64), gw - 1)
        np.add.at(points, (b, r, c), 1)
    sig = np.full((nb, gh, gw), np.nan)
    if sigma is not None:
        cu = (np.arange(gw) + 0.5) * w / gw
        cv = (np.arange(gh) + 0.5) * h / gh
        uu, vv = np.meshgrid(cu, cv)
        uv_c = np.stack([uu.ravel(), vv.ravel()], axis=1)
        mids = 0.5 * (spec.height_edges_mm[:-1] + spec.height_edges_mm[1:])
        for k, zb in enumerate(mids):
            s = np.asarray(sigma(uv_c, np.full(len(uv_c), zb)), np.float64).reshape(gh, gw)
            sig[k] = np.where(np.isfinite(s), np.abs(s), np.nan)
    return CoverageMap(spec, (w, h), points, sig, len(poses))


def suggest_pose(cov: CoverageMap, poses: Sequence[PoseGeometry]) -> PoseAdvice:
    """The next board pose: where the calibrated volume lacks most, tilted as no pose was yet.

    With no pose: the reference plane (flat, farthest, centre). Otherwise the image ninth and
    height bin with the most cells not yet calibrated (ties: the farther from the image centre,
    then the lower bin), and of the four tilt combinations (±25° about each image axis) the one
    the poses so far used least. Once the target is reached the advice says so (more poses
    only tighten σ_model).
    """
    w, h = cov.image_size
    if not poses:
        return PoseAdvice(
            "centre",
            w / 2,
            h / 2,
            0.0,
            0.0,
            0.0,
            "lay the board flat at the farthest distance (pose 0, the reference plane), "
            "centred in the view",
        )
    nb, gh, gw = cov.points.shape
    missing = ~cov.calibrated
    best: tuple[int, int, int] | None = None
    where = (0, 1, 1)
    for b in range(nb):
        for i in range(3):
            for j in range(3):
                block = missing[b, i * gh // 3 : (i + 1) * gh // 3, j * gw // 3 : (j + 1) * gw // 3]
                key = (int(block.sum()), abs(i - 1) + abs(j - 1), -b)
                if best is None or key > best:
                    best, where = key, (b, i, j)
    b, i, j = where
    region = "-".join(x for x in (_ROWS[i], _COLS[j]) if x) or "centre"
    edges = cov.spec.height_edges_mm
    height = float(0.5 * (edges[b] + edges[b + 1]))
    used = np.zeros((2, 2), np.int64)
    for p in poses:
        if abs(p.tilt_vertical_deg) >= TILTED_DEG or abs(p.tilt_horizontal_deg) >= TILTED_DEG:
            used[int(p.tilt_vertical_deg < 0), int(p.tilt_horizontal_deg < 0)] += 1
    a, c = np.unravel_index(int(np.argmin(used)), used.shape)
    tv = -SUGGESTED_TILT_DEG if a else SUGGESTED_TILT_DEG
    th = -SUGGESTED_TILT_DEG if c else SUGGESTED_TILT_DEG
    place = "the centre of the view" if region == "centre" else f"the {region}"
    text = (
        f"move the board to {place}, about {height:.0f} mm above the reference plane, and tilt it "
        f"{abs(tv):.0f} deg about the vertical axis ({'right' if tv > 0 else 'left'} edge toward "
        f"the scope) and {abs(th):.0f} deg about the horizontal axis "
        f"({'bottom' if th > 0 else 'top'} edge toward the scope)"
    )
    if cov.reached:
        text = (
            f"target reached ({100 * cov.calibrated_share:.0f} % of cells calibrated): solve now; "
            f"or, to tighten sigma_model further, {text}"
        )
    cu = (j + 0.5) * w / 3
    cv_ = (i + 0.5) * h / 3
    return PoseAdvice(region, float(cu), float(cv_), height, tv, th, text)


# -- board poses from detections (the wizard's quick view, before any solve) ------------------


@dataclass(frozen=True)
class BoardViews:
    """A quick camera fit to the detected boards: enough to place each pose in the volume.

    Attributes:
        camera_matrix: (3, 3); dist_coeffs: (5,) OpenCV.
        plane: the reference plane (pose 0's board plane, normal toward the scope).
        poses: per view its :class:`PoseGeometry`.
        image_size: (width, height), px.

    ``rays`` maps pixels (n, 2) to undistorted normalised rays (n, 2).
    """

    camera_matrix: F64
    dist_coeffs: F64
    plane: ReferencePlane
    poses: list[PoseGeometry]
    image_size: tuple[int, int]

    def rays(self, uv: F64) -> F64:
        pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
        out = cv2.undistortPoints(pts, self.camera_matrix, self.dist_coeffs)
        return np.asarray(out, np.float64).reshape(-1, 2)


def board_views(
    image_points: Sequence[npt.ArrayLike],
    object_points: Sequence[npt.ArrayLike],
    image_size: tuple[int, int],
    *,
    grid: int = 13,
) -> BoardViews:
    """Camera and board poses from detected board points (view 0 the reference plane).

    A quick fit for guidance, not the calibration: one view takes a nominal focal length (the
    image width; its heights are 0 by definition); two fit the focal length alone; three or
    more the focal lengths, principal point and k1.

    Args:
        image_points: per view (n, 2) pixels (u, v) of the detected board points.
        object_points: per view (n, 3) board coordinates, mm (z = 0).
        image_size: (width, height), px.
        grid: each view's board is sampled on grid × grid points over its corners' extent.
    """
    if not image_points or len(image_points) != len(object_points):
        raise ValueError(
            f"image_points: need one array per view of object_points, got "
            f"{len(image_points)} and {len(object_points)}"
        )
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in image_points]
    obj = [np.asarray(p, np.float32).reshape(-1, 3) for p in object_points]
    w, h = (int(x) for x in image_size)
    cam = np.array([[float(w), 0.0, (w - 1) / 2], [0.0, float(w), (h - 1) / 2], [0.0, 0.0, 1.0]])
    dist = np.zeros(5)
    fixed = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3
    )
    if len(img) == 1:
        ok, rvec, tvec = cv2.solvePnP(obj[0], img[0], cam, dist)
        if not ok:
            raise ValueError("image_points: the board pose could not be solved")
        rvecs, tvecs = [rvec], [tvec]
    else:
        flags = fixed
        if len(img) == 2:
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K1
        _, cam_fit, dist_fit, rv, tv = cv2.calibrateCamera(obj, img, (w, h), cam, dist, flags=flags)
        cam, dist = np.asarray(cam_fit, np.float64), np.asarray(dist_fit, np.float64).ravel()
        rvecs, tvecs = list(rv), list(tv)
    rots = [cv2.Rodrigues(np.asarray(r, np.float64))[0] for r in rvecs]
    normal = np.asarray(rots[0][:, 2], np.float64).copy()
    t0 = np.asarray(tvecs[0], np.float64).ravel()
    if float(normal @ t0) > 0:
        normal = -normal
    offset = -float(normal @ t0)
    x_ax = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    x_ax /= np.linalg.norm(x_ax)
    y_ax = np.cross(normal, x_ax)
    if y_ax[1] < 0:
        y_ax = -y_ax
    out = []
    for o, rot, t in zip(obj, rots, tvecs, strict=True):
        lo, hi = o[:, :2].min(axis=0), o[:, :2].max(axis=0)
        s, tt = np.meshgrid(np.linspace(lo[0], hi[0], grid), np.linspace(lo[1], hi[1], grid))
        board = np.stack([s.ravel(), tt.ravel(), np.zeros(s.size)], axis=1)
        tvec = np.asarray(t, np.float64).ravel()
        uv, _ = cv2.projectPoints(board, cv2.Rodrigues(rot)[0], tvec, cam, dist)
        xyz = board @ rot.T + tvec
        n_k = rot[:, 2] if float(rot[:, 2] @ tvec) < 0 else -rot[:, 2]
        c = float(n_k @ normal)
        out.append(
            PoseGeometry(
                uv.reshape(-1, 2).astype(np.float64),
                xyz @ normal + offset,
                math.degrees(math.atan2(-float(n_k @ x_ax), c)),
                math.degrees(math.atan2(-float(n_k @ y_ax), c)),
            )
        )
    return BoardViews(cam, dist, ReferencePlane(normal, offset), out, (w, h))


def model_sigma(
    views: BoardViews,
    phases: Sequence[npt.NDArray[np.floating]],
    image_points: Sequence[npt.ArrayLike],
    *,
    fringes: int,
    projector_width_px: int,
) -> SigmaFn | None:
    """σ_model from a quick geometric-model fit to the board corners' phases: the jackknife over
    poses (:meth:`GeometricModel.height_sigma`); None with fewer than three poses or when the
    corners do not determine the model.

    Args:
        views: :func:`board_views` of the same poses.
        phases: per pose its (H, W) unwrapped finest phase, rad (NaN invalid).
        image_points: per pose (n, 2) the detected board points.
        fringes: the finest frequency's fringe count; projector_width_px: its axis length, px.
    """
    from app.calib.fitting import sample_phase  # the sampler of the fit itself

    if len(phases) < 3 or len(phases) != len(views.poses) or len(image_points) != len(phases):
        return None
    us, vs, zs, ps, pose = [], [], [], [], []
    cam, dist = views.camera_matrix, views.dist_coeffs
    plane = views.plane
    for k, (ph, ip) in enumerate(zip(phases, image_points, strict=True)):
        uv = np.asarray(ip, np.float64).reshape(-1, 2)
        rays = views.rays(uv)
        # the corners' heights: on pose k's plane fitted through the dense samples
        g = views.poses[k]
        z = _heights_on_plane(g, uv, rays, cam, dist, plane)
        us.append(uv[:, 0])
        vs.append(uv[:, 1])
        zs.append(z)
        ps.append(sample_phase(ph, uv))
        pose.append(np.full(len(uv), k, np.int64))
    u, v = np.concatenate(us), np.concatenate(vs)
    samples = BoardSamples(
        u,
        v,
        views.rays(np.stack([u, v], axis=1)),
        np.concatenate(ps),
        np.concatenate(zs),
        np.concatenate(pose),
        views.image_size,
        int(fringes),
        int(projector_width_px),
    )
    try:
        model = GeometricModel.fit(samples, plane)
    except (ValueError, np.linalg.LinAlgError):
        return None
    return geometric_sigma(model, plane, views.rays)


def geometric_sigma(
    model: GeometricModel, plane: ReferencePlane, rays: Callable[[F64], F64]
) -> SigmaFn | None:
    """σ_model of a fitted geometric model (its jackknife), or None when it has none (a model
    read from a file)."""
    if len(model.jackknife) < 3:
        return None

    def sigma(uv: F64, height_mm: F64) -> F64:
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        return model.height_sigma(
            uv[:, 0], uv[:, 1], rays(uv), np.asarray(height_mm, np.float64), plane
        )

    return sigma


def report_coverage(
    samples: BoardSamples,
    plane: ReferencePlane,
    rays: Callable[[F64], F64],
    model: GeometricModel | None,
    spec: CoverageSpec | None = None,
) -> tuple[CoverageMap, PoseAdvice]:
    """Coverage and the next pose after a fit: its control points per pose (their board tilt from
    a plane through each pose's points) and σ_model of its geometric model (None: no σ).

    Args:
        samples: the fit's control points (``CalibrationReport.samples``).
        plane: the reference plane; rays: pixels (n, 2) → undistorted normalised rays (n, 2).
        model: the fitted geometric model (``CalibrationReport.geometric``) or None.
    """
    pts = samples.points_mm(plane)
    n0 = np.asarray(plane.normal, np.float64)
    x_ax = np.array([1.0, 0.0, 0.0]) - n0[0] * n0
    x_ax /= np.linalg.norm(x_ax)
    y_ax = np.cross(n0, x_ax)
    y_ax = y_ax if y_ax[1] >= 0 else -y_ax
    poses = []
    for k in np.unique(samples.pose):
        sel = samples.pose == k
        p = pts[sel]
        _, _, vt = np.linalg.svd(p - p.mean(axis=0))
        n_k = vt[2] if float(vt[2] @ n0) >= 0 else -vt[2]
        c = float(n_k @ n0)
        poses.append(
            PoseGeometry(
                np.stack([samples.u[sel], samples.v[sel]], axis=1),
                samples.z_mm[sel],
                math.degrees(math.atan2(-float(n_k @ x_ax), c)),
                math.degrees(math.atan2(-float(n_k @ y_ax), c)),
            )
        )
    sigma = None if model is None else geometric_sigma(model, plane, rays)
    cov = coverage_map(poses, samples.image_size, sigma=sigma, spec=spec)
    return cov, suggest_pose(cov, poses)


def _heights_on_plane(
    g: PoseGeometry, uv: F64, rays: F64, cam: F64, dist: F64, plane: ReferencePlane
) -> F64:
    """Heights (mm) of pixels ``uv`` on the board plane of pose ``g``: its dense samples' points
    fitted by a plane (camera frame), the pixels' rays intersected with it."""
    r_s = np.concatenate(
        [
            np.asarray(cv2.undistortPoints(g.uv.reshape(-1, 1, 2), cam, dist), np.float64).reshape(
                -1, 2
            ),
            np.ones((len(g.uv), 1)),
        ],
        axis=1,
    )
    n = np.asarray(plane.normal, np.float64)
    pts = r_s * ((g.height_mm - plane.offset_mm) / (r_s @ n))[:, None]
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre)
    nk = vt[2]
    r = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    x = r * ((nk @ centre) / (r @ nk))[:, None]
    return np.asarray(x @ n + plane.offset_mm, np.float64)
