"""Acceptance figures of a reconstruction against ground truth (used by the end-to-end test
and ``benchmarks/bench_accuracy.py``): plane target, sphere target, feature height.

Callers supply the truth (e.g. from the simulator) and the per-pixel intensity noise σ_I
predicted by their noise model; nothing here knows where they came from.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from app.analysis.groundtruth import depth_errors, perpendicular_noise_mm
from app.analysis.noise import height_noise_mm
from app.analysis.plane import plane_accuracy
from app.analysis.sphere import sphere_figures
from app.core.calibration import Calibration
from app.core.depth_model import SupportedRegion
from app.core.reasons import Reason
from app.core.schedule import PatternSchedule


def background_codes(result: Any) -> npt.NDArray[np.float64]:
    """Background A (codes) of a reconstruction: texture (A + B) minus modulation B."""
    return np.asarray(result.texture, np.float64) - np.asarray(result.modulation, np.float64)


#: a ninth's mean error may reach this where the calibration knows its heights well, mm
BIAS_MM = 0.005
#: σ_model (RMS over a ninth) below which the calibration counts as knowing its heights well, mm
MODEL_SIGMA_SMALL_MM = 0.0025


def bias_limit_mm(model_sigma_mm: float) -> float:
    """The largest |mean error| (mm) a region of the image may show: :data:`BIAS_MM` where
    the calibration's own σ (``model_sigma_mm``, the RMS of ``ReconResult.sigma_model`` over
    the region's valid pixels) is at most :data:`MODEL_SIGMA_SMALL_MM`, else 2·σ_model — the
    calibration's error there is one draw shared by the region's pixels, and 2σ holds it 95 %
    of the time (NaN σ_model, i.e. none given: :data:`BIAS_MM`)."""
    if not model_sigma_mm > MODEL_SIGMA_SMALL_MM:
        return BIAS_MM
    return 2.0 * float(model_sigma_mm)


def _valid_share(result: Any, mask: npt.NDArray[np.bool_]) -> float:
    """Share of the ``mask`` pixels that ``result`` marks valid (NaN for an empty mask)."""
    return float(np.asarray(result.valid, bool)[mask].mean()) if mask.any() else math.nan


def noise_floor_mm(calibration: Calibration, result: Any,
                   sigma_i_dn: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Per-pixel predicted height noise σ_z (mm) of a reconstruction for
    intensity noise σ_I (codes)."""
    if result.phase is None:
        raise ValueError("result: has no phase; make the Reconstructor with with_phase=True")
    return height_noise_mm(calibration, result.phase, sigma_i_dn, result.modulation)


def plane_target_report(calibration: Calibration, result: Any, truth_depth: npt.ArrayLike,
                        sigma_i_dn: npt.ArrayLike, *, exclude: npt.ArrayLike | None = None,
                        supported: npt.ArrayLike | None = None) -> dict[str, Any]:
    """Figures of a flat target (e.g. the 45° DOF target) against its true depth.

    Args:
        calibration: the calibration used.
        result: a ``ReconResult`` (depth, points, valid, phase, modulation).
        truth_depth: (H, W) true height, mm, NaN off-object.
        sigma_i_dn: (H, W) or scalar intensity noise σ_I, codes.
        exclude: optional (H, W) bool pixels left out of the valid-fraction figure
            (e.g. black print, where low modulation is the correct answer).
        supported: optional (H, W) bool pixels whose true (height, phase) lie inside the
            calibration's supported region (:func:`supported_mask`): the valid fraction counts
            only those (the acceptance's "lit, unsaturated pixels inside the supported region").

    Returns:
        dict with ``valid_fraction`` (inside the calibrated volume, after ``exclude``),
        ``valid_fraction_all``, ``mean_error_mm``, ``max_abs_error_mm``, ``rms_error_mm``,
        ``outside_valid``, ``outside_max_abs_error_mm``, the paper's ``accuracy_mm``,
        ``precision_mm`` and ``flatness_mm``, the predicted ``noise_floor_mm`` for that
        precision and ``precision_ratio``; ``depth_precision_mm`` (pooled std of depth
        error in bins of true height) with its ``depth_noise_floor_mm``.
    """
    truth = np.asarray(truth_depth, np.float64)
    errs = depth_errors(result.depth, truth, calibration.height_range_mm)
    lo, hi = calibration.height_range_mm
    inside = np.isfinite(truth) & (truth >= lo) & (truth <= hi)
    keep = inside if exclude is None else inside & ~np.asarray(exclude, bool)
    if supported is not None:
        keep = keep & np.asarray(supported, bool)
    sz = noise_floor_mm(calibration, result, sigma_i_dn)
    valid_in = np.asarray(result.valid, bool) & inside
    pa = plane_accuracy(result.points, valid_in)
    sp = perpendicular_noise_mm(sz, result.points, pa.plane.normal, calibration.plane_normal)
    floor = float(np.sqrt(np.nanmean(sp[valid_in] ** 2)))
    depth_floor = float(np.sqrt(np.nanmean(sz[valid_in] ** 2)))
    return {
        "valid_fraction": _valid_share(result, keep),
        "valid_fraction_all": errs.valid_fraction,
        "inside_pixels": errs.inside_pixels,
        "mean_error_mm": errs.mean_error_mm,
        "max_abs_error_mm": errs.max_abs_error_mm,
        "rms_error_mm": errs.rms_error_mm,
        "outside_pixels": errs.outside_pixels,
        "outside_valid": errs.outside_valid,
        "outside_max_abs_error_mm": errs.outside_max_abs_error_mm,
        "accuracy_mm": pa.accuracy_mm,
        "precision_mm": pa.precision_mm,
        "flatness_mm": pa.flatness_mm,
        "noise_floor_mm": floor,
        "precision_ratio": pa.precision_mm / floor,
        "depth_precision_mm": errs.within_bin_std_mm,
        "depth_noise_floor_mm": depth_floor,
        "depth_precision_ratio": errs.within_bin_std_mm / depth_floor,
    }


def sphere_target_report(calibration: Calibration, result: Any, truth_depth: npt.ArrayLike,
                         truth_points: npt.ArrayLike, centres: list[npt.ArrayLike],
                         radius_mm: float, *, surface_tol_mm: float = 0.02,
                         projector_centre_mm: npt.ArrayLike | None = None,
                         incidence_limits_deg: tuple[float, ...] = (80.0, 87.0),
                         supported: npt.ArrayLike | None = None) -> dict[str, Any]:
    """Figures of sphere targets: validity and error on sphere pixels, then PS/PF per sphere.

    Args:
        centres: true sphere centres (3,) mm, camera frame; radius_mm: their true radius.
        surface_tol_mm: a pixel belongs to a sphere if its true point is this close to it.
        projector_centre_mm: optional (3,) projector centre, camera frame, mm: adds the
            ``incidence`` breakdown (how obliquely the fringes light each sphere pixel).
        incidence_limits_deg: the incidence angles of that breakdown, degrees.
        supported: optional (H, W) bool pixels whose true (height, phase) lie inside the
            calibration's supported region: then ``valid_fraction`` and the breakdowns count
            only those, and ``off_region_pixels`` / ``off_region_valid`` the rest.

    Returns:
        dict with ``valid_fraction`` and error figures over sphere pixels inside the
        calibrated volume, and ``spheres``: per sphere ``diameter_mm``, ``ps_mm``, ``pf_mm``,
        ``rms_mm``, ``n_points``. With ``projector_centre_mm``, ``incidence``: per limit
        ``{"pixels_fraction", "valid_fraction"}`` of the in-volume sphere pixels the
        projector lights at or below that angle, ``unlit_fraction`` (at or beyond 90°:
        in the sphere's own shadow) and ``lit_valid_fraction``: the valid fraction of the
        lit, unsaturated sphere pixels inside the volume (and ``supported``), the whole-field
        issue's acceptance figure.
    """
    tp = np.asarray(truth_points, np.float64)
    on_any = np.zeros(tp.shape[:2], bool)
    normals = np.zeros(tp.shape)
    masks = []
    for c in centres:
        c = np.asarray(c, np.float64)
        m = np.abs(np.linalg.norm(tp - c, axis=-1) - radius_mm) <= surface_tol_mm
        masks.append(m)
        on_any |= m
        normals[m] = (tp[m] - c) / radius_mm
    sup = np.ones(on_any.shape, bool) if supported is None else np.asarray(supported, bool)
    errs = depth_errors(result.depth, truth_depth, calibration.height_range_mm, mask=on_any)
    spheres = []
    for m in masks:
        sel = m & np.asarray(result.valid, bool)
        f = sphere_figures(result.points, 2 * radius_mm, sel, segment=False)
        spheres.append({"diameter_mm": f.diameter_mm, "ps_mm": f.ps_mm, "pf_mm": f.pf_mm,
                        "rms_mm": f.rms_mm, "n_points": f.n_points})
    lo, hi = calibration.height_range_mm
    t = np.asarray(truth_depth, np.float64)
    with np.errstate(invalid="ignore"):
        in_volume = on_any & np.isfinite(t) & (t >= lo) & (t <= hi)
    inside = in_volume & sup
    bad = inside & ~np.asarray(result.valid, bool)
    codes, counts = np.unique(np.asarray(result.reason)[bad], return_counts=True)
    report: dict[str, Any] = {
        "valid_fraction": (_valid_share(result, inside) if supported is not None
                           else errs.valid_fraction),
        "invalid_reasons": {int(c): int(n) for c, n in zip(codes, counts, strict=True)},
        "inside_pixels": errs.inside_pixels,
        "mean_error_mm": errs.mean_error_mm,
        "max_abs_error_mm": errs.max_abs_error_mm,
        "spheres": spheres,
        "off_region_pixels": int((in_volume & ~sup).sum()),
        "off_region_valid": int((in_volume & ~sup & np.asarray(result.valid, bool)).sum()),
    }
    if projector_centre_mm is not None:
        cos_inc = projector_incidence_cos(tp, normals, projector_centre_mm)
        report["unlit_fraction"] = (float((cos_inc[inside] <= 0.0).mean()) if inside.any()
                                    else math.nan)
        lit_unsat = inside & (cos_inc > 0.0) & (np.asarray(result.reason) != Reason.SATURATED)
        report["lit_valid_fraction"] = _valid_share(result, lit_unsat)
        report["incidence"] = {}
        for deg in incidence_limits_deg:
            lit = inside & (cos_inc >= math.cos(math.radians(deg)))
            report["incidence"][float(deg)] = {
                "pixels_fraction": float(lit.sum() / max(1, inside.sum())),
                "valid_fraction": _valid_share(result, lit),
            }
    return report


def projector_incidence_cos(points: npt.ArrayLike, normals: npt.ArrayLike,
                            projector_centre_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Cosine of the angle between surface normals and the rays from the projector.

    Args:
        points: (..., 3) surface points, mm; normals: (..., 3) unit outward normals;
        projector_centre_mm: (3,) projector centre, mm, same frame.

    Returns:
        (...) float64 cos of the incidence angle: 1 face-on, ≤ 0 unlit (facing away).
    """
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    c = np.asarray(projector_centre_mm, np.float64)
    if p.shape[-1] != 3 or n.shape != p.shape:
        raise ValueError(f"normals: shape {n.shape} must equal points {p.shape} (..., 3)")
    if c.shape != (3,) or not np.isfinite(c).all():
        raise ValueError(f"projector_centre_mm: expected 3 finite numbers, got {c.tolist()}")
    to_projector = c - p
    dist = np.linalg.norm(to_projector, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray((n * to_projector).sum(-1) / dist, np.float64)


def true_phase_rad(fringe_coordinate_px: npt.ArrayLike,
                   schedule: PatternSchedule) -> npt.NDArray[np.float64]:
    """The finest frequency's unwrapped phase (rad) a projector coordinate carries.

    Args:
        fringe_coordinate_px: (...) continuous projector coordinate along the fringe axis
            (pixel centres at integers), e.g. a simulator's true projector column of each pixel.
        schedule: the pattern schedule (its last frequency K and axis length L).

    Returns:
        (...) float64 ``2π·K·x / L`` (the pattern of DESIGN.md: ``cos(2π k x / w + δ)``).
    """
    x = np.asarray(fringe_coordinate_px, np.float64)
    k_last, axis_length = float(schedule.frequencies[-1]), float(schedule.axis_length)
    return np.asarray(2.0 * math.pi * k_last / axis_length * x, np.float64)


def supported_mask(region: SupportedRegion, truth_depth: npt.ArrayLike,
                   phase_rad: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """(H, W) True where the true (height, phase) of a pixel lies inside a
    calibration's supported region.

    Args:
        region: the depth model's :class:`~app.core.depth_model.SupportedRegion`.
        truth_depth: (H, W) true height, mm (NaN off-object: not supported).
        phase_rad: (H, W) true finest unwrapped phase, rad (:func:`true_phase_rad`).
    """
    t = np.asarray(truth_depth, np.float64)
    p = np.asarray(phase_rad, np.float64)
    if t.ndim != 2 or p.shape != t.shape:
        raise ValueError(f"phase_rad: shape {p.shape} does not match truth_depth {t.shape} (H, W)")
    return np.asarray(~region.outside(t, p) & np.isfinite(t) & np.isfinite(p), np.bool_)


def ninths_report(result: Any, truth_depth: npt.ArrayLike, height_range_mm: tuple[float, float],
                  sigma_mm: npt.ArrayLike, *, lit: npt.ArrayLike | None = None,
                  gross_mm: float = 0.5, grid: tuple[int, int] = (3, 3),
                  supported: npt.ArrayLike | None = None,
                  sigma_model_mm: npt.ArrayLike | None = None) -> list[dict[str, Any]]:
    """Acceptance figures in each cell of a ``grid`` (rows, cols) split of the image
    — every ninth by default.

    Args:
        result: a ``ReconResult`` (``depth`` (H, W) mm NaN invalid, ``valid`` (H, W) bool,
            ``reason`` (H, W) uint8 :class:`~app.core.reasons.Reason`).
        truth_depth: (H, W) true height, mm, NaN off-object.
        height_range_mm: (lo, hi) calibrated height range, mm: inside it a pixel is "in the volume".
        sigma_mm: (H, W) predicted 1-σ depth noise per pixel, mm (e.g. ``ReconResult.sigma``).
        lit: optional (H, W) bool: pixels the projector lights (default: every pixel with a truth).
        gross_mm: an error beyond this on a valid pixel is gross.
        grid: (rows, cols) of the split.
        supported: optional (H, W) bool: pixels whose TRUE (height, phase) lie inside the
            calibration's supported region (:func:`supported_mask`); default: all.
        sigma_model_mm: optional (H, W) the calibration's own 1-σ per pixel, mm
            (``ReconResult.sigma_model``): each cell's ``model_sigma_mm`` and ``bias_limit_mm``.

    Returns:
        One dict per cell, row-major: ``row``, ``col``; inside (in the volume and the supported
        region): ``pixels`` (lit, unsaturated),
        ``valid_fraction``, ``mean_error_mm``, ``rms_mm``, ``floor_mm`` (RMS of ``sigma_mm`` over
        the same valid pixels), ``rms_ratio`` (rms / floor), ``std_ratio`` (std / floor), ``gross``
        (valid pixels with |error| > gross_mm), ``max_abs_error_mm``; outside the volume:
        ``outside_pixels``, ``outside_valid``, ``outside_gross``, ``outside_max_abs_error_mm``;
        in the volume but outside the supported region (lit): ``off_region_pixels``,
        ``off_region_valid``, ``off_region_gross``, ``off_region_max_abs_error_mm``;
        ``model_sigma_mm`` (RMS of ``sigma_model_mm`` over the valid inside pixels; NaN
        without it) and ``bias_limit_mm`` (:func:`bias_limit_mm` of it).
        Figures of an empty set are NaN.
    """
    depth = np.asarray(result.depth, np.float64)
    truth = np.asarray(truth_depth, np.float64)
    sig = np.asarray(sigma_mm, np.float64)
    valid = np.asarray(result.valid, bool)
    if truth.shape != depth.shape:
        raise ValueError(f"truth_depth: shape {truth.shape} does not match depth {depth.shape}")
    if sig.shape != depth.shape:
        raise ValueError(f"sigma_mm: shape {sig.shape} does not match depth {depth.shape}")
    model = None if sigma_model_mm is None else np.asarray(sigma_model_mm, np.float64)
    if model is not None and model.shape != depth.shape:
        raise ValueError(f"sigma_model_mm: shape {model.shape} does not match depth {depth.shape}")
    rows, cols = (int(g) for g in grid)
    if rows < 1 or cols < 1:
        raise ValueError(f"grid: need positive (rows, cols), got {grid}")
    lo, hi = (float(x) for x in height_range_mm)
    if not lo < hi:
        raise ValueError(f"height_range_mm: need lo < hi, got {height_range_mm}")
    lit_m = np.isfinite(truth) if lit is None else np.asarray(lit, bool) & np.isfinite(truth)
    sup = np.ones(depth.shape, bool) if supported is None else np.asarray(supported, bool)
    if sup.shape != depth.shape:
        raise ValueError(f"supported: shape {sup.shape} does not match depth {depth.shape}")
    unsat = np.asarray(result.reason) != Reason.SATURATED
    with np.errstate(invalid="ignore"):
        in_volume = lit_m & (truth >= lo) & (truth <= hi)
        inside = in_volume & sup
        off_region = in_volume & ~sup
        outside = lit_m & ~((truth >= lo) & (truth <= hi))
    err = depth - truth
    h, w = depth.shape
    ys = np.linspace(0, h, rows + 1).round().astype(int)
    xs = np.linspace(0, w, cols + 1).round().astype(int)
    nan = math.nan
    cells = []
    for r in range(rows):
        for c in range(cols):
            win = (slice(ys[r], ys[r + 1]), slice(xs[c], xs[c + 1]))
            ins = inside[win] & unsat[win]
            ok = ins & valid[win]
            e = err[win][ok]
            s = sig[win][ok]
            s = s[np.isfinite(s)]
            floor = float(np.sqrt(np.mean(s**2))) if s.size else nan
            rms = float(np.sqrt(np.mean(e**2))) if e.size else nan
            out_m = outside[win]
            out_ok = out_m & valid[win]
            eo = np.abs(err[win][out_ok])
            off_m = off_region[win]
            off_ok = off_m & valid[win]
            ef = np.abs(err[win][off_ok])
            sm = nan if model is None else model[win][ok]
            sm_rms = float(np.sqrt(np.mean(np.square(sm)))) if np.size(sm) else nan
            cells.append({
                "row": r, "col": c, "pixels": int(ins.sum()),
                "valid_fraction": float(ok.sum() / ins.sum()) if ins.any() else nan,
                "mean_error_mm": float(e.mean()) if e.size else nan,
                "rms_mm": rms,
                "floor_mm": floor,
                "rms_ratio": rms / floor if e.size and floor > 0 else nan,
                "std_ratio": float(e.std()) / floor if e.size > 1 and floor > 0 else nan,
                "gross": int((np.abs(e) > gross_mm).sum()),
                "max_abs_error_mm": float(np.abs(e).max()) if e.size else nan,
                "outside_pixels": int(out_m.sum()),
                "outside_valid": int(out_ok.sum()),
                "outside_gross": int((eo > gross_mm).sum()),
                "outside_max_abs_error_mm": float(eo.max()) if eo.size else nan,
                "off_region_pixels": int(off_m.sum()),
                "off_region_valid": int(off_ok.sum()),
                "off_region_gross": int((ef > gross_mm).sum()),
                "off_region_max_abs_error_mm": float(ef.max()) if ef.size else nan,
                "model_sigma_mm": sm_rms,
                "bias_limit_mm": bias_limit_mm(sm_rms),
            })
    return cells
