"""Height of a raised feature (a suture) over the surrounding surface, as a caliper would see it.

The feature is segmented by an intensity threshold on the texture image (optionally
also by its height over a first baseline), a smooth baseline surface is fitted to a
ring of pixels around it, and the crest height above that baseline is taken in every
cross-section along the feature's length: its mean ± std is the feature height.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from app.analysis.common import roi_mask

F64 = npt.NDArray[np.float64]


@dataclass
class FeatureHeight:
    """Result of :func:`feature_height`.

    Attributes:
        height_mm: mean crest height over the cross-sections, mm.
        height_std_mm: standard deviation of the crest heights, mm.
        count: cross-sections measured.
        mask: (H, W) bool segmented feature pixels.
        crest_heights_mm: (count,) per cross-section crest heights, mm.
        baseline_rms_mm: RMS residual of the baseline surface fit, mm.
    """

    height_mm: float
    height_std_mm: float
    count: int
    mask: npt.NDArray[np.bool_]
    crest_heights_mm: F64
    baseline_rms_mm: float


def feature_height(depth: npt.ArrayLike, texture: npt.ArrayLike, valid: npt.ArrayLike | None = None, *,
                   roi: tuple[int, int, int, int] | None = None, threshold: float | None = None,
                   polarity: str = "bright", height_threshold_mm: float | None = None,
                   ring_px: tuple[int, int] = (4, 16), min_area_px: int = 30,
                   min_section_px: int = 3, slab_px: float = 3.0) -> FeatureHeight:
    """Crest height of a feature over a fitted baseline.

    Args:
        depth: (H, W) float height map, mm, NaN invalid.
        texture: (H, W) intensity image (any numeric range) used for segmentation.
        valid: optional (H, W) bool mask (combined with finiteness of ``depth``).
        roi: (x0, y0, x1, y1) pixel box (x1, y1 exclusive) around the feature.
        threshold: intensity threshold; default Otsu's threshold inside the ROI.
        polarity: ``"bright"`` (feature brighter than surroundings) or ``"dark"``.
        height_threshold_mm: if given, feature pixels must also stand this high above a
            first baseline fitted to the whole ROI.
        ring_px: (inner, outer) distance in pixels of the baseline ring from the feature.
        min_area_px: connected segments smaller than this are ignored.
        min_section_px: cross-sections with fewer feature pixels are skipped.
        slab_px: half-length along the feature of the flank pixels used for each
            cross-section's local baseline line.

    Returns:
        A :class:`FeatureHeight`.
    """
    z = np.asarray(depth, np.float64)
    tex = np.asarray(texture, np.float64)
    if z.ndim != 2:
        raise ValueError(f"depth: expected (H, W), got shape {z.shape}")
    if tex.shape != z.shape:
        raise ValueError(f"texture: shape {tex.shape} does not match depth {z.shape}")
    if polarity not in ("bright", "dark"):
        raise ValueError(f"polarity: must be 'bright' or 'dark', got {polarity!r}")
    inner, outer = (int(r) for r in ring_px)
    if not 0 <= inner < outer:
        raise ValueError(f"ring_px: need 0 <= inner < outer, got {ring_px}")
    area = roi_mask(z.shape, roi)
    ok = area & np.isfinite(z) & np.isfinite(tex)
    if valid is not None:
        v = np.asarray(valid, bool)
        if v.shape != z.shape:
            raise ValueError(f"valid: shape {v.shape} does not match depth {z.shape}")
        ok &= v
    if ok.sum() < 50:
        raise ValueError(f"depth: only {int(ok.sum())} valid pixels in the ROI")
    if threshold is None:
        threshold = _otsu(tex[ok])
    mask = area & ((tex > threshold) if polarity == "bright" else (tex < threshold))
    if height_threshold_mm is not None:
        first, _ = _fit_baseline(z, ok)
        mask &= (z - first) > height_threshold_mm
    labels, comps = _components(mask, min_area_px)
    if not comps:
        raise ValueError("threshold: no feature segment found in the ROI")
    mask = np.isin(labels, comps)
    near = cv2.dilate(mask.astype(np.uint8), _disk(inner)) > 0 if inner else mask
    far = cv2.dilate(mask.astype(np.uint8), _disk(outer)) > 0
    ring = far & ~near & ok
    if ring.sum() < 20:
        raise ValueError("ring_px: too few valid baseline pixels around the feature")
    baseline, rms = _fit_baseline(z, ring)
    resid = z - baseline
    crests: list[float] = []
    for c in comps:
        crests += _crest_heights(resid, (labels == c) & ok, ring, min_section_px, slab_px, outer + 1)
    if not crests:
        raise ValueError("depth: no cross-section of the feature has enough valid pixels")
    arr = np.asarray(crests)
    return FeatureHeight(
        height_mm=float(arr.mean()),
        height_std_mm=float(arr.std(ddof=1)) if len(arr) > 1 else 0.0,
        count=len(arr),
        mask=mask,
        crest_heights_mm=arr,
        baseline_rms_mm=rms,
    )


def _crest_heights(resid: F64, seg: npt.NDArray[np.bool_], ring: npt.NDArray[np.bool_], min_px: int,
                   slab_px: float, reach_px: float) -> list[float]:
    """Crest per 1-px cross-section across the segment's long axis.

    In each cross-section the baseline is refined by a line through the ring pixels on
    both flanks (within ``slab_px`` along the axis), as a caliper rests on both sides;
    the crest is a parabola through the central part of the profile, evaluated on the
    feature's axis (:func:`_crests_on_axis`).
    """
    ys, xs = np.nonzero(seg)
    if len(xs) < min_px:
        return []
    xy = np.stack([xs, ys], axis=1).astype(np.float64)
    centre = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - centre, full_matrices=False)
    along = (xy - centre) @ vt[0]
    across = (xy - centre) @ vt[1]
    width = float(np.ptp(across))
    r = resid[ys, xs]
    ry, rx = np.nonzero(ring)
    rxy = np.stack([rx, ry], axis=1).astype(np.float64) - centre
    r_along, r_across = rxy @ vt[0], rxy @ vt[1]
    near = np.abs(r_across) <= 0.5 * width + reach_px  # flanks of this segment, not of a neighbour
    r_along, r_across, r_val = r_along[near], r_across[near], resid[ry, rx][near]
    r_order = np.argsort(r_along)
    r_along, r_across, r_val = r_along[r_order], r_across[r_order], r_val[r_order]
    section = np.rint(along).astype(np.int64)
    fits: list[tuple[float, npt.NDArray[np.float64] | None, float, float, float]] = []
    order = np.argsort(section, kind="stable")
    bounds = np.flatnonzero(np.diff(section[order])) + 1
    for idx in np.split(order, bounds):
        if len(idx) < min_px:
            continue
        s0 = float(section[idx[0]])
        lo, hi = np.searchsorted(r_along, [s0 - slab_px, s0 + slab_px])
        fa, fv = r_across[lo:hi], r_val[lo:hi]
        if (fa < across[idx].min()).sum() < 2 or (fa > across[idx].max()).sum() < 2:
            continue  # a caliper needs ground on both sides
        slope, inter = np.polyfit(fa, fv, 1)
        t, h = across[idx], r[idx] - (slope * across[idx] + inter)
        # The central 60 % of the cross-section, chosen by position (not by value, which
        # would favour upward noise) — the part of a round thread a parabola fits well.
        t_c, half = 0.5 * (t.max() + t.min()), 0.5 * float(np.ptp(t))
        top = np.abs(t - t_c) <= 0.6 * half
        coef = None
        if top.sum() >= 3 and np.ptp(t[top]) > 0:
            # kept whatever its curvature: dropping the noisy ones that curve up would
            # keep a biased (upward) sample
            coef = np.polyfit(t[top], h[top], 2)
        fits.append((s0, coef, float(t[top].min()), float(t[top].max()), float(np.median(np.sort(h)[-3:]))))
    return _crests_on_axis(fits)


def _crests_on_axis(fits: list[tuple[float, npt.NDArray[np.float64] | None, float, float, float]]) -> list[float]:
    """Each cross-section's parabola evaluated on the feature's axis.

    The apex of a noisy parabola, c + b²/4|a|, is biased upward by var(b)/4|a|; the
    value at a fixed position is linear in the coefficients, hence unbiased. The axis
    (the crest's position across the feature, a line along it) comes from all the
    sections' apexes at once, robustly. Sections without a usable parabola give the
    median of their three highest points.
    """
    apex = [(s0, t) for s0, c, lo, hi, _ in fits if (t := _apex(c, lo, hi)) is not None]
    axis = None
    if len(apex) >= 5:
        s_a, t_a = np.asarray(apex).T
        keep = np.ones(len(s_a), bool)
        for _ in range(3):  # clip apexes far from the line: neighbours' knots, bad sections
            axis = np.polyfit(s_a[keep], t_a[keep], 1)
            e = t_a - np.polyval(axis, s_a)
            keep = np.abs(e) <= max(3.0 * 1.4826 * float(np.median(np.abs(e[keep]))), 0.5)
    out = []
    for s0, c, lo, hi, fallback in fits:
        if c is not None and axis is not None and lo <= np.polyval(axis, s0) <= hi:
            out.append(float(np.polyval(c, np.polyval(axis, s0))))
        elif c is not None and axis is None and (t := _apex(c, lo, hi)) is not None:
            out.append(float(np.polyval(c, t)))
        else:
            out.append(fallback)
    return out


def _apex(coef: npt.NDArray[np.float64] | None, lo: float, hi: float) -> float | None:
    """Position of a downward parabola's apex when it lies within [lo, hi], else None."""
    if coef is None or coef[0] >= 0:
        return None
    t = -coef[1] / (2 * coef[0])
    return float(t) if lo <= t <= hi else None


def _fit_baseline(z: F64, sel: npt.NDArray[np.bool_]) -> tuple[F64, float]:
    """Quadratic surface z(u, v) fitted to ``sel`` pixels with 3σ clipping; (H, W) and RMS."""
    h, w = z.shape
    ys, xs = np.nonzero(sel)
    if len(xs) < 6:
        raise ValueError("depth: too few pixels for a baseline surface")
    cx, cy, s = w / 2.0, h / 2.0, max(w, h) / 2.0

    def design(x: F64, y: F64) -> F64:
        x, y = (x - cx) / s, (y - cy) / s
        return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)

    a = design(xs.astype(np.float64), ys.astype(np.float64))
    zz = z[ys, xs]
    keep = np.ones(len(zz), bool)
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(a[keep], zz[keep], rcond=None)
        e = zz - a @ coef
        sigma = 1.4826 * float(np.median(np.abs(e[keep])))
        new = np.abs(e) <= max(3 * sigma, 1e-9)
        if np.array_equal(new, keep):
            break
        keep = new
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return design(xx, yy) @ coef, float(np.sqrt(np.mean(e[keep] ** 2)))


def _components(mask: npt.NDArray[np.bool_], min_area: int) -> tuple[npt.NDArray[np.int32], list[int]]:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_area]
    return np.asarray(labels, np.int32), keep


def _disk(r: int) -> npt.NDArray[np.uint8]:
    return np.asarray(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)), np.uint8)


def _otsu(values: F64) -> float:
    lo, hi = float(values.min()), float(values.max())
    if not hi > lo:
        raise ValueError("texture: constant in the ROI, nothing to segment")
    scaled = np.clip((values - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8).reshape(-1, 1)
    t, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return lo + (float(t) + 0.5) / 255.0 * (hi - lo)


__all__ = ["FeatureHeight", "feature_height"]
