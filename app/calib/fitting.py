"""The calibration procedure: board poses → camera model, reference plane, Eq. (5) fit.

``calibrate_folder`` reads a calibration folder (``board.json`` + ``pose_NN/`` capture
sets); ``calibrate_sets`` does the same for in-memory capture sets; both end in
``fit_observations``, which takes detected board points and phase maps and can be
driven directly with synthetic data.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from app.calib.board import detect_board, load_board, texture_to_u8
from app.calib.camera import (
    DISTORTION_MODELS,
    DISTORTION_TERMS,
    MODEL_LADDER,
    SPLIT,
    CameraFit,
    calibrate_camera,
    calibrate_views,
    field_shortfall,
)
from app.calib.model import undistort_points
from app.calib.refine import (
    NoiseScales,
    RefinedPoses,
    RefinementCheck,
    check_refinement,
    refine_board_poses,
)
from app.capture.captureset import CaptureSet, read_capture_set
from app.core.board import BoardSpec
from app.core.calibration import Calibration
from app.core.depth_model import (
    BoardSamples,
    DepthModel,
    ReferencePlane,
    region_from_samples,
)
from app.core.depth_model_registry import MODEL_NAMES
from app.core.eq5 import Eq5Model, choose_normalization, evaluate, fit_eq5, normalize
from app.core.geometric import MODEL_SIGMA_TOLERANCE_MM, GeometricModel, PipelineFit
from app.core.limits import full_scale
from app.core.schedule import PatternSchedule

MIN_POSES = 3
CALIBRATION_MIN_MODULATION_FRACTION = (
    0.02  # board phases: B ≥ 2 % of full scale (see calibrate_sets)
)
MIN_HEIGHT_SPAN_MM = 1.0
MIN_TILT_SPREAD_DEG = 2.0
ROBUST_POINT_SIGMAS = 4.0
ROBUST_POSE_FACTOR = 3.0
DENSE_POINTS_PER_POSE = 1500
REFINE_POINTS_PER_POSE = 12000  # board pixels per pose whose phase refines the board poses


@dataclass
class PoseObservation:
    """One board pose: detected points and the unwrapped finest-frequency phase map.

    Attributes:
        image_points: (n, 2) float32 pixel coordinates (u, v) of the board points.
        object_points: (n, 3) float32 board coordinates, mm.
        phase: (H, W) float32 unwrapped phase, radians, NaN where invalid.
        name: label for reports (e.g. ``pose_03``).
        modulation: optional (H, W) float32 fringe modulation B of the finest frequency (codes):
            weighs the phase of each board pixel when the poses are refined (σ_φ ∝ 1/B).
    """

    image_points: npt.NDArray[np.float32]
    object_points: npt.NDArray[np.float32]
    phase: npt.NDArray[np.float32]
    name: str = ""
    modulation: npt.NDArray[np.float32] | None = None


@dataclass
class PoseReport:
    """Per-pose figures of a calibration.

    Attributes:
        pose: index; name: label; corners: board points detected; reprojection_px: RMS
        reprojection error of the camera model, px; rms_mm: RMS Eq. (5) residual of the
        pose's points used in the fit, mm; points: points used; dropped_points: points
        rejected (invalid phase or robust outliers); dropped: the whole pose rejected.
        height_mm: (min, max) height of the pose's control points, mm.
    """

    pose: int
    name: str
    corners: int
    reprojection_px: float
    rms_mm: float
    points: int
    dropped_points: int = 0
    dropped: bool = False
    height_mm: tuple[float, float] = (math.nan, math.nan)


@dataclass
class CalibrationReport:
    """The calibration and how well each pose fitted."""

    calibration: Calibration
    poses: list[PoseReport] = field(default_factory=list)
    rms_mm: float = math.nan
    reprojection_px: float = math.nan
    held_out: dict[str, dict[str, float | int | str | None]] = field(default_factory=dict)
    uncovered: list[str] = field(default_factory=list)
    camera: CameraFit | None = None
    #: the control points of the fit and the geometric model fitted to them (with its jackknife,
    #: which files do not keep): what the coverage report (app.calib.coverage) reads
    samples: BoardSamples | None = None
    geometric: GeometricModel | None = None
    refinement: RefinementCheck | None = None  # the joint fit's verdict; None: not tried

    def table(self) -> str:
        """Human-readable per-pose table with totals."""
        head = (
            f"{'pose':>4}  {'name':<10} {'corners':>7} {'reproj_px':>9} {'fit_rms_mm':>10} "
            f"{'points':>6}  {'height_mm':>15}"
        )
        lines = [head, "-" * len(head)]
        for p in self.poses:
            flag = "  DROPPED" if p.dropped else ""
            lines.append(
                f"{p.pose:>4}  {p.name:<10} {p.corners:>7} {p.reprojection_px:>9.3f} "
                f"{p.rms_mm:>10.4f} "
                f"{p.points:>6}  {p.height_mm[0]:>7.2f}..{p.height_mm[1]:<6.2f}{flag}"
            )
        lo, hi = self.calibration.height_range_mm
        lines.append("-" * len(head))
        lines.append(
            f"{'all':>4}  {'':<10} {sum(p.corners for p in self.poses):>7} "
            f"{self.reprojection_px:>9.3f} "
            f"{self.rms_mm:>10.4f} {sum(p.points for p in self.poses):>6}  {lo:>7.2f}..{hi:<6.2f}"
        )
        if self.uncovered:
            lines.append(
                f"no control points in the {', '.join(self.uncovered)} ninth(s) of the image: "
                "Eq. (5) does not support depth there"
            )
        if self.camera is not None:
            lines.extend(self._camera_lines(self.camera))
        if self.refinement is not None:
            lines.append(self.refinement.reason)
        lines.extend(self._projector_lines())
        if self.held_out:
            lines.append("")
            lines.append(
                f"{'model':<10} {'held-out rms_mm':>15} {'held-out max_mm':>15} {'points':>7}  "
                "(leave one pose out)"
            )
            active = self.calibration.model.name
            for name, h in self.held_out.items():
                if h.get("error"):
                    lines.append(
                        f"{name:<10} {'-':>15} {'-':>15} {'-':>7}  not fitted: {h['error']}"
                    )
                    continue
                mark = "  <- active" if name == active else ""
                lines.append(
                    f"{name:<10} {_fmt(h.get('rms_mm')):>15} {_fmt(h.get('max_mm')):>15} "
                    f"{h.get('points', 0):>7}{mark}"
                )
        return "\n".join(lines)

    def _projector_lines(self) -> list[str]:
        """The projector columns (rows for horizontal fringes) the active model supports: a
        surface lit from beyond them has no depth (OUTSIDE_FIELD) — place boards where those
        columns fall."""
        rng = self.calibration.model.region.phase_rad
        sched = self.calibration.pattern
        if rng is None:
            return []
        extent = sched.axis_length
        scale = extent / (2.0 * math.pi * float(sched.frequencies[-1]))
        lo, hi = max(0.0, rng[0] * scale), min(float(extent), rng[1] * scale)
        axis = "columns" if sched.orientation == "vertical" else "rows"
        lines = [
            f"projector field supported: {axis} {lo:.0f}..{hi:.0f} of {extent} "
            "(the boards' phase range "
            "and its margin); surfaces lit from outside it have no depth"
        ]
        grid = self.calibration.model.region.height_grid_mm
        if self.calibration.model.name == "geometric" and grid is not None:
            z_lo, z_hi = self.calibration.height_range_mm
            span = np.clip(
                np.minimum(grid[..., 1], z_hi) - np.maximum(grid[..., 0], z_lo), 0.0, None
            )
            share = float(span.mean() / (z_hi - z_lo)) if z_hi > z_lo else math.nan
            lines.append(
                f"depth model verified in {100 * share:.0f} % of the calibrated volume "
                "(image cells x "
                f"heights): the boards' data, and beyond them where its own 1-sigma uncertainty is "
                f"<= {1000 * MODEL_SIGMA_TOLERANCE_MM:.1f} um"
            )
        return lines

    def _camera_lines(self, cam: CameraFit) -> list[str]:
        held = ", ".join(f"{k} {_fmt(v)}" for k, v in cam.held_out_px.items())
        lines = [
            f"lens distortion: {cam.model} (held-out reprojection px, corners beyond "
            f"r = {SPLIT * cam.r_max:.3f} fitted from the inner ones: {held or 'not measurable'})"
        ]
        if math.isfinite(cam.field_radius):
            short = field_shortfall(cam.field_px(), self.calibration.image_size)
            where = ", ".join(f"{k} {100 * v:.0f} %" for k, v in short.items())
            model = self.calibration.model
            beyond = (
                "depth there only where the calibration's own sigma (its refits and the next "
                "lens model's disagreement) passes the gross-error rule"
                if isinstance(model, GeometricModel) and model.lens_alternative is not None
                else "no depth there"
            )
            lines.append(
                f"corner-verified lens field: normalised radius <= {cam.field_radius:.3f} "
                "(board corners reach "
                f"{cam.r_max:.3f}); "
                + (f"beyond it ({where}): {beyond}" if where else "the whole image")
            )
        return lines


def _fmt(x: object) -> str:
    return f"{x:.4f}" if isinstance(x, float) and math.isfinite(x) else "-"


def sample_phase(phase: npt.NDArray[np.floating], points: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Bilinear phase at sub-pixel points; NaN where any of the 2×2 neighbours is invalid.

    Args:
        phase: (H, W) float phase map, radians, NaN invalid.
        points: (n, 2) pixel coordinates (u = column, v = row).

    Returns:
        (n,) float64 radians.
    """
    ph = np.asarray(phase)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if ph.ndim != 2:
        raise ValueError(f"phase: expected (H, W), got shape {ph.shape}")
    h, w = ph.shape
    u, v = pts[:, 0], pts[:, 1]
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    out = np.full(len(pts), np.nan)
    i0, j0 = v0[inside], u0[inside]
    fu, fv = u[inside] - j0, v[inside] - i0
    p = ph.astype(np.float64)
    q00, q01, q10, q11 = p[i0, j0], p[i0, j0 + 1], p[i0 + 1, j0], p[i0 + 1, j0 + 1]
    # NaN in any neighbour propagates: those points are refused, not extrapolated.
    out[inside] = (q00 * (1 - fu) + q01 * fu) * (1 - fv) + (q10 * (1 - fu) + q11 * fu) * fv
    return out


def calibrate_folder(calib_dir: str | os.PathLike[str], *, robust: bool = False,
                     dense: bool = True, model: str | None = None) -> CalibrationReport:
    """Calibrate from a folder with ``board.json`` and capture sets ``pose_00/``, ``pose_01/``, …"""
    folder = Path(calib_dir)
    if not folder.is_dir():
        raise ValueError(f"{folder}: calibration folder not found")
    board = load_board(folder / "board.json")
    pose_dirs = sorted(p for p in folder.glob("pose_*") if p.is_dir())
    if not pose_dirs:
        raise ValueError(f"{folder}: no pose_NN/ capture sets")
    if pose_dirs[0].name != "pose_00":
        raise ValueError(f"{folder}: pose_00/ (the reference plane) is missing")
    sets = [read_capture_set(p) for p in pose_dirs]
    return calibrate_sets(
        board, sets, robust=robust, dense=dense, names=[p.name for p in pose_dirs], model=model
    )


@dataclass(frozen=True)
class ObservedSet:
    """What the fit needs of one board capture set once it has been looked at.

    The frames themselves are no longer needed: a calibration session keeps this per pose
    (about 11 MB at 1384 x 1032) instead of the whole fringe set (tens of MB).

    Attributes:
        schedule: the set's pattern schedule.
        frame_shape: (F, H, W) of its frames.
        observation: the board's points and the finest phase (its name not yet given), None
            where the board was not found in the set's texture.
    """

    schedule: PatternSchedule
    frame_shape: tuple[int, int, int]
    observation: PoseObservation | None


def observe_set(board: BoardSpec, cs: CaptureSet) -> ObservedSet:
    """Compute the phase of a board capture set and find the board in its texture.

    Args:
        board: the board shown.
        cs: (F, H, W) frames of one pose with their schedule.
    """
    from app.recon import compute_phase  # the engine; imported late so I/O stays optional

    # a fixed 2 % of full scale, not the noise-aware rule: the fit has plenty of bright board
    # pixels and wants the least-biased ones (dim squares add noise, not information)
    max_code = capture_max_code(cs)
    res = compute_phase(
        cs.frames,
        cs.schedule,
        max_code=max_code,
        min_modulation=CALIBRATION_MIN_MODULATION_FRACTION
        * (max_code or np.iinfo(cs.frames.dtype).max),
    )
    det = detect_board(texture_to_u8(res.texture), board)
    shape = (int(cs.frames.shape[0]), int(cs.frames.shape[1]), int(cs.frames.shape[2]))
    if not det.found:
        return ObservedSet(cs.schedule, shape, None)
    obs = PoseObservation(det.image_points, det.object_points, res.phase, "", res.modulation)
    return ObservedSet(cs.schedule, shape, obs)


def _check_observed(board: BoardSpec, observed: ObservedSet, first: ObservedSet, i: int,
                    name: str, robust: bool) -> None:
    """Raise the ValueError of :func:`calibrate_sets` for pose ``i`` (mismatch, no board)."""
    if observed.schedule != first.schedule or observed.frame_shape != first.frame_shape:
        raise ValueError(f"pose {i} ({name}): pattern or frame size differs from pose 0")
    if observed.observation is None and (not robust or i == 0):
        raise ValueError(
            f"pose {i} ({name}): board not found ({board.type} {board.cols}x{board.rows})"
        )


def calibrate_sets(
    board: BoardSpec,
    sets: list[CaptureSet],
    *,
    robust: bool = False,
    dense: bool = True,
    names: list[str] | None = None,
    model: str | None = None,
) -> CalibrationReport:
    """Calibrate from capture sets of the board, ``sets[0]`` being the reference plane.

    Raises:
        ValueError: too few poses, board not found (naming the pose), mismatched sets,
            too little depth span or degenerate tilts.
    """
    if len(sets) < MIN_POSES:
        raise ValueError(f"poses: need at least {MIN_POSES} board poses, got {len(sets)}")
    names = names or [f"pose_{i:02d}" for i in range(len(sets))]
    observed: list[ObservedSet] = []
    for i, (cs, name) in enumerate(zip(sets, names, strict=True)):
        if cs.schedule != sets[0].schedule or cs.frames.shape != sets[0].frames.shape:
            # before the phase: a mismatched set costs no computation
            raise ValueError(f"pose {i} ({name}): pattern or frame size differs from pose 0")
        observed.append(observe_set(board, cs))
        _check_observed(board, observed[-1], observed[0], i, name, robust)
    return calibrate_observed(board, observed, robust=robust, dense=dense, names=names,
                              model=model)


def calibrate_observed(
    board: BoardSpec,
    observed: list[ObservedSet],
    *,
    robust: bool = False,
    dense: bool = True,
    names: list[str] | None = None,
    model: str | None = None,
) -> CalibrationReport:
    """:func:`calibrate_sets` from sets already looked at (:func:`observe_set`), ``observed[0]``
    being the reference plane; the same checks and errors.

    Raises:
        ValueError: as :func:`calibrate_sets`.
    """
    if len(observed) < MIN_POSES:
        raise ValueError(f"poses: need at least {MIN_POSES} board poses, got {len(observed)}")
    names = names or [f"pose_{i:02d}" for i in range(len(observed))]
    observations: list[PoseObservation | None] = []
    for i, (seen, name) in enumerate(zip(observed, names, strict=True)):
        _check_observed(board, seen, observed[0], i, name, robust)
        obs = seen.observation
        observations.append(None if obs is None else replace(obs, name=name))
    first = observed[0].frame_shape
    image_size = (first[2], first[1])
    return fit_observations(
        observations, image_size, observed[0].schedule, robust=robust, dense=dense, names=names,
        model=model
    )


def fit_observations(
    observations: list[PoseObservation | None],
    image_size: tuple[int, int],
    schedule: PatternSchedule,
    *,
    robust: bool = False,
    dense: bool = True,
    names: list[str] | None = None,
    model: str | None = None,
    refine: bool = True,
) -> CalibrationReport:
    """Camera calibration, reference plane and the depth models' fits from detected poses.

    Both models (Eq. (5) and the geometric one) are fitted and judged on held-out poses
    (leave one pose out); the one with the smaller held-out RMS (Eq. (5) by at least 2 %,
    :data:`EQ5_PREFERENCE`) becomes the calibration's active model unless ``model``
    (``"eq5"`` or ``"geometric"``) names one.

    Args:
        observations: per pose, or None for a pose whose board was not found (robust mode);
            index 0 is the reference plane.
        image_size: (width, height) of the frames, pixels.
        schedule: the fringe schedule the phase maps came from.
        robust: drop outlier points (> 4σ by MAD) and outlier poses (RMS > 3× median), and refit.
        dense: besides the corners (which give the camera model and the board planes), use
            a grid of pixels over each board (its control grid plus half a pitch) as phase
            control points: their heights come from the board plane and the calibrated
            camera rays. Many more, better spread points than the corners alone (the
            paper's choice, ``dense=False``), hence a better conditioned Eq. (5) fit.
        refine: with ``dense``, refine the board poses (and so the reference plane) jointly
            with the projector by the phase over each board (:mod:`app.calib.refine`): a
            small board's tilt from its corners alone is loose, and pose 0's tilt is the
            reference plane's.
    """
    if model is not None and model not in MODEL_NAMES:
        raise ValueError(f"model: must be one of {list(MODEL_NAMES)}, got {model!r}")
    names = names or [f"pose_{i:02d}" for i in range(len(observations))]
    found = [i for i, o in enumerate(observations) if o is not None]
    if not observations or observations[0] is None:
        raise ValueError("pose 0: board not found (pose 0 defines the reference plane)")
    if len(found) < MIN_POSES:
        raise ValueError(
            f"poses: need at least {MIN_POSES} poses with the board found, got {len(found)}"
        )
    obs = [observations[i] for i in found]
    obj = [np.ascontiguousarray(o.object_points, np.float32) for o in obs]  # type: ignore[union-attr]
    img = [np.ascontiguousarray(o.image_points, np.float32).reshape(-1, 1, 2) for o in obs]  # type: ignore[union-attr]
    camfit = calibrate_camera(obj, img, image_size)
    rms_px, cam, dist, rvecs, tvecs = (
        camfit.rms_px,
        camfit.camera_matrix,
        camfit.dist_coeffs,
        camfit.rvecs,
        camfit.tvecs,
    )
    rots = [cv2.Rodrigues(r)[0] for r in rvecs]
    normals = np.array([r[:, 2] for r in rots])
    tilt = max(
        math.degrees(math.acos(min(1.0, abs(float(a @ b))))) for a in normals for b in normals
    )
    if tilt < MIN_TILT_SPREAD_DEG:
        raise ValueError(
            f"poses: degenerate tilts — all boards within {tilt:.1f}° of each other; "
            "tilt the board "
            f"by at least {MIN_TILT_SPREAD_DEG:.0f}° between poses "
            "so the camera model is determined"
        )
    refined, refinement = None, None
    if dense and refine:
        free = DISTORTION_TERMS[camfit.model]
        refined = _refine_with_phase(obs, obj, img, cam, dist, rvecs, tvecs, schedule, free)
        if refined is None:
            refinement = RefinementCheck(
                False, float(rms_px), math.nan, math.nan, math.nan, math.nan, 0,
                "phase refinement not possible (too few phase points on a board, or the joint fit "
                "failed): the corners-only camera and poses are kept")
        else:
            # the joint fit must not spoil the camera: else the corners-only one stands
            refinement = check_refinement(obj, img, cam, dist, rvecs, tvecs, refined, free)
            if not refinement.accepted:
                refined = None
        if refined is not None:
            rvecs, tvecs = refined.rvecs, refined.tvecs
            rots = [cv2.Rodrigues(r)[0] for r in rvecs]
            cam, dist = refined.camera_matrix, refined.dist_coeffs
            camfit.camera_matrix, camfit.dist_coeffs = cam, dist
            rms_px = refined.reprojection_px
    # Reference plane: pose 0's board plane, unit normal toward the camera centre.
    normal = rots[0][:, 2].astype(np.float64)
    if float(normal @ tvecs[0].ravel()) > 0:
        normal = -normal
    offset = -float(normal @ tvecs[0].ravel())

    per_pose = []
    for k, o in enumerate(obs):
        proj, _ = cv2.projectPoints(obj[k], rvecs[k], tvecs[k], cam, dist)
        reproj = float(
            np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img[k].reshape(-1, 2)) ** 2, axis=1)))
        )
        if dense:
            uv, z_k, phi_k = _dense_samples(o, rvecs[k], tvecs[k], cam, dist, normal, offset)  # type: ignore[arg-type]
        else:
            cam_pts = (rots[k] @ obj[k].T.astype(np.float64)).T + tvecs[k].ravel()
            uv = o.image_points.astype(np.float64)  # type: ignore[union-attr]
            z_k = cam_pts @ normal + offset
            phi_k = sample_phase(o.phase, o.image_points)  # type: ignore[union-attr]
        per_pose.append((z_k, phi_k, reproj, uv, len(o.image_points)))  # type: ignore[union-attr]

    u = np.concatenate([p[3][:, 0] for p in per_pose])
    v = np.concatenate([p[3][:, 1] for p in per_pose])
    z = np.concatenate([p[0] for p in per_pose])
    phi = np.concatenate([p[1] for p in per_pose])
    pose_of = np.concatenate([np.full(len(p[0]), k) for k, p in enumerate(per_pose)])
    use = np.isfinite(phi)
    dropped_pose = np.zeros(len(obs), bool)
    for k in range(len(obs)):
        if not np.any(use[pose_of == k]):
            if k == 0 or not robust:
                raise ValueError(
                    f"pose {found[k]} ({names[found[k]]}): no control point has a valid phase"
                )
            dropped_pose[k] = True

    if robust and len(obs) >= 4:
        held_bad = _held_out_outliers(u, v, phi, z, pose_of, use, image_size)
        for k in range(1, len(obs)):
            sel = (pose_of == k) & use
            if sel.any() and held_bad[sel].mean() > 0.5:
                dropped_pose[k] = True
        use &= ~held_bad & ~dropped_pose[pose_of]

    for _ in range(4 if robust else 1):
        _check_span(z[use])
        norm = choose_normalization(u[use], v[use], phi[use], z[use], image_size)
        un, vn, pn = normalize(norm, u, v, phi)
        fit = fit_eq5(un[use], vn[use], pn[use], z[use])
        res_all = np.full(len(z), np.nan)
        res_all[use] = fit.residuals_mm
        if not robust:
            break
        new_use = use.copy()
        sigma = 1.4826 * float(np.median(np.abs(fit.residuals_mm)))
        new_use &= np.abs(np.nan_to_num(res_all, nan=np.inf)) <= max(
            ROBUST_POINT_SIGMAS * sigma, 1e-6
        )
        pose_rms = np.array([_rms(res_all[(pose_of == k) & use]) for k in range(len(obs))])
        med = float(np.nanmedian(pose_rms))
        for k in range(1, len(obs)):
            if pose_rms[k] > ROBUST_POSE_FACTOR * med and pose_rms[k] > 1e-3:
                dropped_pose[k] = True
        new_use &= ~dropped_pose[pose_of]
        if np.array_equal(new_use, use):
            break
        use = new_use

    reports: list[PoseReport] = []
    k_of = {i: k for k, i in enumerate(found)}
    for i in range(len(observations)):
        if i not in k_of:
            reports.append(PoseReport(i, names[i], 0, math.nan, math.nan, 0, 0, True))
            continue
        k = k_of[i]
        sel = pose_of == k
        hz = z[sel]
        reports.append(
            PoseReport(
                pose=i,
                name=names[i],
                corners=per_pose[k][4],
                reprojection_px=per_pose[k][2],
                rms_mm=_rms(res_all[sel & use]),
                points=int((sel & use).sum()),
                dropped_points=int((sel & ~use).sum()),
                dropped=bool(dropped_pose[k]),
                height_mm=(float(hz.min()), float(hz.max())),
            )
        )
    uv_all = np.stack([u, v], axis=1)
    ray_xy = undistort_points(uv_all, cam, dist)
    samples = BoardSamples(
        u[use],
        v[use],
        ray_xy[use],
        phi[use],
        z[use],
        pose_of[use].astype(np.int64),
        image_size,
        int(schedule.frequencies[-1]),
        int(schedule.width),
    )
    uncovered = _check_coverage(samples)
    plane = ReferencePlane(normal, offset)
    field_px = camfit.field_px()
    models: dict[str, DepthModel] = {
        "eq5": Eq5Model(
            fit.numerator,
            fit.denominator,
            norm,
            region_from_samples(samples).field_limited(field_px),
        )
    }
    held_out: dict[str, dict[str, float | int | str | None]] = {}
    try:
        geo = GeometricModel.fit(samples, plane)
        joint = None
        if refined is not None:  # the refits repeat the joint fit the calibration kept
            joint = _JointFit(obs, schedule, DISTORTION_TERMS[camfit.model], cam, dist, rvecs,
                              tvecs, refined.projector, refined.noise_scales)
        geo.pipeline = _pipeline_jackknife(obj, img, image_size, camfit.model, samples, geo, joint)
        if geo.pipeline:
            geo.lens_alternative = _lens_alternative(obj, img, image_size, camfit.model, samples,
                                                     geo, joint)
            geo.lens_verified_px = field_px
        # the field where the lens model is defined: beyond the corners' reach the refits' spread
        # and the next lens model's row (σ_model) decide, pixel by pixel
        geo.region = geo.region.field_limited(
            camfit.defined_field_px() if geo.pipeline else field_px)
        # where the model's own (jackknife) uncertainty passes the gross-error rule, and no farther
        geo.region = geo.verified_region(
            image_size,
            plane,
            lambda uv: undistort_points(uv, cam, dist),
            (float(z[use].min()), float(z[use].max())),
        )
        models["geometric"] = geo
    except ValueError as exc:
        if model == "geometric":
            raise
        held_out["geometric"] = {"error": str(exc)}
    for name, fitted in models.items():
        left_out: list[DepthModel] = []
        held_out[name] = _held_out_errors(name, samples, plane, left_out)
        if isinstance(fitted, Eq5Model):  # its jackknife: the held-out fits (geometric: its own)
            fitted.jackknife = [m for m in left_out if isinstance(m, Eq5Model)]
    if model is None:
        model = _better_model(models, held_out)
    calibration = Calibration(
        camera_matrix=cam,
        dist_coeffs=dist.ravel(),
        image_size=image_size,
        plane_normal=normal,
        plane_offset_mm=offset,
        model=models[model],
        held_out=held_out,
        pattern=schedule,
        height_range_mm=(float(z[use].min()), float(z[use].max())),
        pose_residuals=[
            {
                "pose": r.pose,
                "name": r.name,
                "corners": r.corners,
                "reprojection_px": _num(r.reprojection_px),
                "rms_mm": _num(r.rms_mm),
                "points": r.points,
                "dropped": r.dropped,
            }
            for r in reports
        ],
        extra={"camera_model": camfit.summary()},
    )
    geo_fit = models.get("geometric")
    if refinement is not None:
        calibration.extra["refinement"] = refinement.to_dict()
    return CalibrationReport(
        calibration,
        reports,
        rms_mm=_rms(res_all[use]),
        reprojection_px=float(rms_px),
        held_out=held_out,
        uncovered=uncovered,
        camera=camfit,
        samples=samples,
        geometric=geo_fit if isinstance(geo_fit, GeometricModel) else None,
        refinement=refinement,
    )


def _key(x: object) -> float:
    return x if isinstance(x, float) and math.isfinite(x) else math.inf


#: Eq. (5) must beat the geometric model's held-out RMS by this factor to be kept: the
#: physical model extrapolates with the geometry (its supported region is the projector's
#: field, not only the cells the boards reached), so on a tie it is the better choice.
EQ5_PREFERENCE = 0.98


def _better_model(
    models: dict[str, DepthModel], held_out: dict[str, dict[str, float | int | str | None]]
) -> str:
    if "geometric" not in models:
        return "eq5"
    eq5, geo = _key(held_out["eq5"].get("rms_mm")), _key(held_out["geometric"].get("rms_mm"))
    return "eq5" if eq5 < EQ5_PREFERENCE * geo else "geometric"


def _held_out_errors(
    name: str, samples: BoardSamples, plane: ReferencePlane, fitted: list[DepthModel] | None = None
) -> dict[str, float | int | str | None]:
    """Leave-one-pose-out height errors (mm) of model ``name``: fit on the other poses,
    evaluate on the left-out one; RMS and max |error| over all left-out points. The
    leave-one-out fits are appended to ``fitted`` when given."""
    kind: type[DepthModel] = Eq5Model if name == "eq5" else GeometricModel
    errors, where = [], []
    poses = np.unique(samples.pose)
    for k in poses:
        train = samples.subset(samples.pose != k)
        test = samples.subset(samples.pose == k)
        try:
            _check_span(train.z_mm)
            m = kind.fit(train, plane)
        except ValueError:
            continue  # the others alone do not determine the model
        if fitted is not None:
            fitted.append(m)
        errors.append(m.height_at(test.u, test.v, test.ray_xy, test.phi, plane) - test.z_mm)
        where.append(_board_points(test, plane))
    if not errors:
        return {"rms_mm": None, "max_mm": None, "points": 0, "poses": 0}
    e = np.concatenate(errors)
    e = np.where(np.isfinite(e), e, np.inf)
    out: dict[str, float | int | str | None] = {
        "rms_mm": _num(_rms(e)) if np.all(np.isfinite(e)) else None,
        "max_mm": _num(float(np.max(np.abs(e)))), "points": int(e.size), "poses": len(errors)}
    if np.all(np.isfinite(e)):
        out.update(error_structure(errors, where))
    return out


def _board_points(s: BoardSamples, plane: ReferencePlane) -> npt.NDArray[np.float64]:
    """The 3-D points (camera frame, mm) of board samples: their rays at their board heights."""
    rays = np.column_stack([s.ray_xy, np.ones(len(s.z_mm))])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (s.z_mm - plane.offset_mm) / (rays @ np.asarray(plane.normal, np.float64))
    return np.asarray(rays * t[:, None], np.float64)


#: distance bins (mm) of the held-out errors' variogram and the correlation lengths tried (mm)
_VARIOGRAM_BINS_MM = np.geomspace(0.25, 256.0, 31)
_CORRELATION_GRID_MM = np.geomspace(0.5, 500.0, 61)


def error_structure(errors: list[npt.NDArray[np.float64]], points: list[npt.NDArray[np.float64]],
                    max_points: int = 1500, seed: int = 0) -> dict[str, float | None]:
    """Split held-out height errors into an independent and a smooth (correlated) part.

    Fits the empirical semivariogram of the errors within each held-out pose,
    ``γ(d) = ½ E[(e_i − e_j)²]`` over pairs ``d`` mm apart, with ``γ(d) = n² + s²(1 − exp(−d/L))``:
    ``n`` the independent part (the board points' own phase noise, which a measurement's
    noise σ already counts), ``s`` the calibration's systematic error per point and ``L``
    its correlation length. ``s²`` is then the errors' mean square less ``n²``, so the
    two parts add up to the held-out RMS.

    Args:
        errors: per held-out pose its height errors, mm, shape (N_k,).
        points: per held-out pose the samples' 3-D points, mm, shape (N_k, 3).
        max_points: at most this many samples per pose (a seeded random subset) enter the pairs.
        seed: the subset's seed.

    Returns:
        ``{"noise_mm", "systematic_mm", "correlation_mm"}``; None each if too few pairs.
    """
    if len(errors) != len(points):
        raise ValueError(
            f"points: need one array per pose of errors ({len(errors)}), got {len(points)}"
        )
    rng = np.random.default_rng(seed)
    nb = len(_VARIOGRAM_BINS_MM) - 1
    ssum, dsum, cnt = np.zeros(nb), np.zeros(nb), np.zeros(nb)
    for e, x in zip(errors, points, strict=True):
        e, x = np.asarray(e, np.float64), np.asarray(x, np.float64)
        ok = np.isfinite(e) & np.all(np.isfinite(x), axis=1)
        e, x = e[ok], x[ok]
        if len(e) > max_points:
            keep = rng.choice(len(e), max_points, replace=False)
            e, x = e[keep], x[keep]
        d, g = _pair_distances_and_semivariances(x, e)
        b = np.searchsorted(_VARIOGRAM_BINS_MM, d) - 1
        inb = (b >= 0) & (b < nb)
        np.add.at(ssum, b[inb], g[inb])
        np.add.at(dsum, b[inb], d[inb])
        np.add.at(cnt, b[inb], 1.0)
    use = cnt >= 10
    if use.sum() < 3:
        return {"noise_mm": None, "systematic_mm": None, "correlation_mm": None}
    gam, dist, w = ssum[use] / cnt[use], dsum[use] / cnt[use], np.sqrt(cnt[use])
    allerr = np.concatenate([np.asarray(e, np.float64) for e in errors])
    ms = float(np.mean(allerr[np.isfinite(allerr)] ** 2))
    best: tuple[float, float, float] | None = None
    for length_mm in _CORRELATION_GRID_MM:
        a = np.column_stack([np.ones_like(dist), 1.0 - np.exp(-dist / length_mm)])
        coef, *_ = np.linalg.lstsq(a * w[:, None], gam * w, rcond=None)
        n2 = float(np.clip(coef[0], 0.0, ms))
        s2 = max(0.0, float(coef[1]))
        cost = float(np.sum((w * (a @ np.array([n2, s2]) - gam)) ** 2))
        if best is None or cost < best[0]:
            best = (cost, n2, float(length_mm))
    assert best is not None
    _, n2, length_mm = best
    return {"noise_mm": _num(math.sqrt(n2)), "systematic_mm": _num(math.sqrt(max(0.0, ms - n2))),
            "correlation_mm": _num(length_mm)}


def _pair_distances_and_semivariances(
    x: npt.NDArray[np.float64], e: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Every pair i < j of one pose's samples (row-major, as ``np.triu_indices(n, 1)``): its
    distance ``|x_i − x_j|`` (mm) and half squared error difference ``½ (e_i − e_j)²`` (mm²).

    Args:
        x: (n, 3) float64 sample points, mm.
        e: (n,) float64 height errors, mm.

    Returns:
        Two (n (n − 1) / 2,) float64 arrays. ``pdist`` computes only the pairs the variogram
        uses: the full (n, n, 3) difference array took ~8x the time at n = 1500 (54 MB), for
        the same values bit for bit (both sum the three squared components in order).
    """
    from scipy.spatial.distance import pdist  # late, as the other scipy solvers here

    i, j = np.triu_indices(len(e), 1)
    return np.asarray(pdist(x), np.float64), 0.5 * (e[i] - e[j]) ** 2


#: the boards' control points must span at least this fraction of the image width and height
MIN_COVERED_SPAN = 0.25


def _check_coverage(samples: BoardSamples) -> list[str]:
    """The ninths of the image without control points (the supported region excludes them).

    A bench board often covers only the central part of the field; that is accepted. Too little
    is a set of control points whose extent does not contain the image centre or spans less than
    :data:`MIN_COVERED_SPAN` of the width or height: ``ValueError`` naming the empty ninths."""
    w, h = samples.image_size
    col = np.clip((samples.u * 3 // w).astype(np.int64), 0, 2)
    row = np.clip((samples.v * 3 // h).astype(np.int64), 0, 2)
    hit = np.zeros((3, 3), bool)
    hit[row, col] = True
    if hit.all():
        return []
    rows, cols = ("top", "middle", "bottom"), ("left", "centre", "right")
    missing = [
        "centre" if (i, j) == (1, 1) else f"{rows[i]} {cols[j]}"
        for i in range(3)
        for j in range(3)
        if not hit[i, j]
    ]
    u_lo, u_hi, v_lo, v_hi = samples.u.min(), samples.u.max(), samples.v.min(), samples.v.max()
    holds_centre = (u_lo <= w / 2 <= u_hi) and (v_lo <= h / 2 <= v_hi)
    if (
        holds_centre
        and (u_hi - u_lo) >= MIN_COVERED_SPAN * w
        and (v_hi - v_lo) >= MIN_COVERED_SPAN * h
    ):
        return missing
    raise ValueError(
        "poses: the boards cover too little of the field — no control point in the "
        f"{', '.join(missing)} "
        f"ninth{'s' if len(missing) > 1 else ''} of the image; place the board so it reaches there"
    )


def _held_out_outliers(
    u: npt.NDArray[np.float64],
    v: npt.NDArray[np.float64],
    phi: npt.NDArray[np.float64],
    z: npt.NDArray[np.float64],
    pose_of: npt.NDArray[np.int64],
    use: npt.NDArray[np.bool_],
    image_size: tuple[int, int],
) -> npt.NDArray[np.bool_]:
    """Points far off a fit of the *other* poses (leave one pose out), e.g. a fringe-order slip.

    A corrupted pose pulls an in-sample fit toward itself, hiding its own residuals; held
    out, its points are judged by the rest. Far = more than 10 robust σ of the in-sample
    residuals and 0.05 mm.
    """
    bad = np.zeros(len(z), bool)
    for k in np.unique(pose_of[use]):
        if k == 0:
            continue  # the reference pose defines the plane; never judged out
        train = use & (pose_of != k)
        test = use & (pose_of == k)
        try:
            _check_span(z[train])
            norm = choose_normalization(u[train], v[train], phi[train], z[train], image_size)
            un, vn, pn = normalize(norm, u, v, phi)
            fit = fit_eq5(un[train], vn[train], pn[train], z[train])
        except ValueError:
            continue  # the others alone do not determine the model: no verdict
        sigma = 1.4826 * float(np.median(np.abs(fit.residuals_mm)))
        r = evaluate(fit.numerator, fit.denominator, un[test], vn[test], pn[test]) - z[test]
        idx = np.flatnonzero(test)
        bad[idx] = ~(np.abs(r) <= max(10.0 * sigma, 0.05))
    return bad


def _dense_samples(
    o: PoseObservation,
    rvec: npt.NDArray[np.float64],
    tvec: npt.NDArray[np.float64],
    cam: npt.NDArray[np.float64],
    dist: npt.NDArray[np.float64],
    normal: npt.NDArray[np.float64],
    offset: float,
    target: int = DENSE_POINTS_PER_POSE,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Pixels on a grid over the board: (n, 2) pixel coordinates, heights (mm), phases (rad,
    NaN invalid)."""
    obj = o.object_points.astype(np.float64)
    d = np.linalg.norm(obj[:, None, :2] - obj[None, :, :2], axis=2)
    d[d == 0] = np.inf
    margin = 0.5 * float(np.median(d.min(axis=1)))
    lo, hi = obj[:, :2].min(axis=0) - margin, obj[:, :2].max(axis=0) + margin
    edge = np.linspace(0.0, 1.0, 16)
    outline = np.concatenate([
        np.stack([lo[0] + edge * (hi[0] - lo[0]), np.full(16, lo[1])], 1),
        np.stack([np.full(16, hi[0]), lo[1] + edge * (hi[1] - lo[1])], 1),
        np.stack([hi[0] - edge * (hi[0] - lo[0]), np.full(16, hi[1])], 1),
        np.stack([np.full(16, lo[0]), hi[1] - edge * (hi[1] - lo[1])], 1),
    ])
    outline3 = np.concatenate([outline, np.zeros((len(outline), 1))], axis=1)
    poly, _ = cv2.projectPoints(outline3, rvec, tvec, cam, dist)
    h, w = o.phase.shape
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [np.rint(poly.reshape(-1, 2)).astype(np.int32)], 1)
    step = max(1, round(math.sqrt(max(1, int(mask.sum())) / target)))
    ys, xs = np.mgrid[step // 2 : h - 1 : step, step // 2 : w - 1 : step]
    keep = mask[ys, xs] > 0
    xs, ys = xs[keep].astype(np.float64), ys[keep].astype(np.float64)
    phi = o.phase[ys.astype(np.int64), xs.astype(np.int64)].astype(np.float64)
    uv = np.stack([xs, ys], axis=1)
    rays = undistort_points(uv, cam, dist)
    rays = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    rmat = cv2.Rodrigues(rvec)[0]
    n_k, t_k = rmat[:, 2], np.asarray(tvec, np.float64).ravel()
    pts = rays * ((n_k @ t_k) / (rays @ n_k))[:, None]
    return uv, pts @ normal + offset, phi


def capture_max_code(cs: CaptureSet) -> int | None:
    """The sensor's maximum code from a capture set's optional ``bit_depth`` (DESIGN.md), else None
    (the dtype's full range): 12-bit frames in uint16 must not be judged against 65535."""
    bits = getattr(cs, "bit_depth", None) or cs.extra.get("bit_depth")
    if bits is None:
        return None
    if isinstance(bits, bool) or not isinstance(bits, int) or not 8 <= bits <= 16:
        raise ValueError(f"bit_depth: must be an integer within 8–16, got {bits!r}")
    return full_scale(bits)


def _refine_with_phase(
    obs: list[PoseObservation | None],
    obj: list[npt.NDArray[np.float32]],
    img: list[npt.NDArray[np.float32]],
    cam: npt.NDArray[np.float64],
    dist: npt.NDArray[np.float64],
    rvecs: list[npt.NDArray[np.float64]],
    tvecs: list[npt.NDArray[np.float64]],
    schedule: PatternSchedule,
    free_dist: tuple[int, ...],
) -> RefinedPoses | None:
    """Board poses refined jointly with the projector by the phase over each board
    (:mod:`app.calib.refine`); None leaves the corner poses."""
    px = _phase_pixels(obs, cam, dist, rvecs, tvecs, schedule, REFINE_POINTS_PER_POSE)
    weights = [w for _, _, w in px if w is not None]
    return refine_board_poses(
        obj,
        img,
        cam,
        dist,
        rvecs,
        tvecs,
        [p for p, _, _ in px],
        [x for _, x, _ in px],
        weights if len(weights) == len(obs) else None,
        free_dist,
    )


def _phase_pixels(
    obs: list[PoseObservation | None],
    cam: npt.NDArray[np.float64],
    dist: npt.NDArray[np.float64],
    rvecs: list[npt.NDArray[np.float64]],
    tvecs: list[npt.NDArray[np.float64]],
    schedule: PatternSchedule,
    target: int,
) -> list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64] | None]]:
    """Per pose about ``target`` board pixels (m, 2), their projector coordinates (m,) (the
    finest phase scaled to projector pixels) and phase weights (m,) (modulation over its
    median; None without a modulation map): the phase data of the joint fit."""
    out: list[
        tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64] | None]
    ] = []
    scale = schedule.width / (2.0 * math.pi * float(schedule.frequencies[-1]))
    for k, o in enumerate(obs):
        assert o is not None
        uv, _, phi_k = _dense_samples(
            o, rvecs[k], tvecs[k], cam, dist, np.array([0.0, 0.0, 1.0]), 0.0, target=target
        )
        w = None
        if o.modulation is not None:
            b = o.modulation[uv[:, 1].astype(np.int64), uv[:, 0].astype(np.int64)].astype(
                np.float64
            )
            w = b / max(float(np.nanmedian(b)), 1e-9)
        out.append((uv, phi_k * scale, w))
    return out


def _board_pose(
    rvec: npt.NDArray[np.float64], tvec: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], float]:
    """A board pose's plane ``normal · X + offset = 0`` (camera frame, mm; normal toward the
    camera centre)."""
    normal = np.asarray(cv2.Rodrigues(np.asarray(rvec, np.float64))[0][:, 2], np.float64)
    t = np.asarray(tvec, np.float64).ravel()
    if float(normal @ t) > 0:
        normal = -normal
    return normal, -float(normal @ t)


#: board pixels per pose whose phase refines each leave-one-pose-out refit: as many as the
#: calibration's own (with a quarter, the refits' spread overstated σ_model 2-3x on the twin)
JACKKNIFE_REFINE_POINTS_PER_POSE = REFINE_POINTS_PER_POSE


@dataclass
class _JointFit:
    """The joint (corners + phase) fit the calibration kept, for its refits to repeat: the
    poses' observations, the schedule, the free distortion terms and its solution (the camera,
    the poses and the projector, (8,) as :attr:`RefinedPoses.projector`) and the noise scales
    it weighed the residuals by."""

    obs: list[PoseObservation | None]
    schedule: PatternSchedule
    free_dist: tuple[int, ...]
    camera_matrix: npt.NDArray[np.float64]
    dist_coeffs: npt.NDArray[np.float64]
    rvecs: list[npt.NDArray[np.float64]]
    tvecs: list[npt.NDArray[np.float64]]
    projector: npt.NDArray[np.float64] | None = None
    noise_scales: NoiseScales | None = None


def _refit_camera(
    obj: list[npt.NDArray[np.float32]],
    img: list[npt.NDArray[np.float32]],
    image_size: tuple[int, int],
    flags: int,
    left: int,
    joint: _JointFit | None,
    pixels: list[
        tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64] | None]
    ],
) -> (
    tuple[
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        dict[int, tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]],
    ]
    | None
):
    """The camera and every board pose with pose ``left`` left out of the fit: the joint fit
    repeated from its solution (camera, poses and projector: no direct linear start) when the
    calibration kept one, else the corners-only fit; pose 0 (the reference plane) left out
    keeps the calibration's own pose and camera (its plane is defined by that board alone).
    None when the fit fails."""
    keep = [k for k in range(len(obj)) if k != left]
    if joint is not None:
        if left == 0:
            return joint.camera_matrix, joint.dist_coeffs, dict(
                enumerate(zip(joint.rvecs, joint.tvecs, strict=True)))
        weights = [w for w in (pixels[k][2] for k in keep) if w is not None]
        refined = refine_board_poses(
            [obj[k] for k in keep], [img[k] for k in keep], joint.camera_matrix,
            joint.dist_coeffs, [joint.rvecs[k] for k in keep], [joint.tvecs[k] for k in keep],
            [pixels[k][0] for k in keep], [pixels[k][1] for k in keep],
            weights if len(weights) == len(keep) else None,
            joint.free_dist, joint.projector,
            None if joint.noise_scales is None else joint.noise_scales.of_views(keep))
        if refined is not None:
            pose_of = {k: (refined.rvecs[i], refined.tvecs[i]) for i, k in enumerate(keep)}
            return refined.camera_matrix, refined.dist_coeffs, pose_of
    try:
        _, cam, dist, rvecs, tvecs = calibrate_views([obj[k] for k in keep], [img[k] for k in keep],
                                                     image_size, flags)
        pose_of = {k: (rvecs[i], tvecs[i]) for i, k in enumerate(keep)}
        if 0 not in pose_of:
            ok, r0, t0 = cv2.solvePnP(obj[0], img[0], cam, dist, flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok:
                return None
            pose_of[0] = (np.asarray(r0, np.float64), np.asarray(t0, np.float64))
    except cv2.error:
        return None
    return cam, dist, pose_of


def _refit_through(cam: npt.NDArray[np.float64], dist: npt.NDArray[np.float64],
                   pose_of: dict[int, tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]],
                   samples: BoardSamples, geo: GeometricModel,
                   left: int | None = None) -> PipelineFit | None:
    """The reference plane (pose 0's board), the samples' heights and the projector refitted
    through the camera ``cam``, ``dist`` and board poses ``pose_of`` (pose index → rvec, tvec),
    pose ``left`` left out; None when the projector cannot be fitted."""
    normal, offset = _board_pose(*pose_of[0])
    plane = ReferencePlane(normal, offset)
    rays = undistort_points(np.column_stack([samples.u, samples.v]), cam, dist)
    r3 = np.column_stack([rays, np.ones(len(rays))])
    z = np.full(len(rays), np.nan)
    for k in (int(k) for k in np.unique(samples.pose)):
        if k == left:
            continue
        sel = samples.pose == k
        n_k, off_k = _board_pose(*pose_of[k])
        with np.errstate(divide="ignore", invalid="ignore"):
            pts = r3[sel] * (-off_k / (r3[sel] @ n_k))[:, None]
        z[sel] = pts @ normal + offset
    train = (samples.pose != left) & np.isfinite(z)
    sub = BoardSamples(samples.u[train], samples.v[train], rays[train], samples.phi[train],
                       z[train], samples.pose[train], samples.image_size, samples.fringes,
                       samples.projector_width_px)
    try:
        projector = geo.refit(sub, plane)
    except ValueError:
        return None
    return PipelineFit(cam, dist[:5].copy(), plane, projector)


def _lens_alternative(obj: list[npt.NDArray[np.float32]], img: list[npt.NDArray[np.float32]],
                      image_size: tuple[int, int], lens_model: str, samples: BoardSamples,
                      geo: GeometricModel, joint: _JointFit | None) -> PipelineFit | None:
    """The whole calibration refitted with the next lens model of the held-out ladder (k1 →
    k1,k2 → k1,k2,p1,p2 → k1,k2,k3,p1,p2) from all poses: the term the held-out test did not
    choose may be real, and beyond the corners' reach the two models' rays part (a dropped k2
    bends every ray past the boards, and no refit of the chosen model shows it). The joint
    corners + phase fit is repeated with the other model's terms when the calibration kept one.
    None after the last model or when a fit fails."""
    if lens_model not in MODEL_LADDER[:-1]:
        return None
    other = MODEL_LADDER[MODEL_LADDER.index(lens_model) + 1]
    try:
        _, cam, dist, rvecs, tvecs = calibrate_views(obj, img, image_size,
                                                     DISTORTION_MODELS[other])
    except cv2.error:
        return None
    if joint is not None:
        pixels = _phase_pixels(joint.obs, cam, dist, rvecs, tvecs, joint.schedule,
                               JACKKNIFE_REFINE_POINTS_PER_POSE)
        weights = [w for (_, _, w) in pixels if w is not None]
        refined = refine_board_poses(
            obj, img, cam, dist, rvecs, tvecs, [p[0] for p in pixels], [p[1] for p in pixels],
            weights if len(weights) == len(pixels) else None, DISTORTION_TERMS[other])
        if refined is not None:
            cam, dist = refined.camera_matrix, refined.dist_coeffs
            rvecs, tvecs = list(refined.rvecs), list(refined.tvecs)
    return _refit_through(cam, dist, dict(enumerate(zip(rvecs, tvecs, strict=True))), samples,
                          geo)


def _pipeline_jackknife(obj: list[npt.NDArray[np.float32]], img: list[npt.NDArray[np.float32]],
                        image_size: tuple[int, int], lens_model: str, samples: BoardSamples,
                        geo: GeometricModel, joint: _JointFit | None = None) -> list[PipelineFit]:
    """The calibration refitted with each board pose left out: the camera (the same lens model)
    and board poses from the other poses (:func:`_refit_camera`: the joint corners + phase fit
    when the calibration kept one), the reference plane (pose 0's board through that camera),
    the samples' rays and heights through both, and the projector
    (:meth:`GeometricModel.refit`) from the other poses' samples.

    The refits' spread is the uncertainty of the camera, its lens model's extrapolation beyond
    the boards, the reference plane and the projector together. Empty with fewer than 3."""
    poses = [int(k) for k in np.unique(samples.pose)]
    if len(poses) < MIN_POSES:
        return []
    flags = DISTORTION_MODELS[lens_model]
    pixels = [] if joint is None else _phase_pixels(
        joint.obs, joint.camera_matrix, joint.dist_coeffs, joint.rvecs, joint.tvecs,
        joint.schedule, JACKKNIFE_REFINE_POINTS_PER_POSE)
    out: list[PipelineFit] = []
    for left in poses:
        fit = _refit_camera(obj, img, image_size, flags, left, joint, pixels)
        if fit is None:
            continue
        refit = _refit_through(*fit, samples, geo, left)
        if refit is not None:
            out.append(refit)
    return out if len(out) >= MIN_POSES else []


def _check_span(z: npt.NDArray[np.float64]) -> None:
    span = float(np.ptp(z)) if z.size else 0.0
    if span < MIN_HEIGHT_SPAN_MM:
        raise ValueError(
            f"poses: control points span only {span:.2f} mm in height; move the board through the "
            f"working volume (need at least {MIN_HEIGHT_SPAN_MM:.0f} mm)"
        )


def _rms(x: npt.NDArray[np.float64]) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else math.nan


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else round(float(x), 6)
