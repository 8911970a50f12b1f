"""Height of a raised feature (a suture) over the surrounding surface, as a caliper would see it.

The feature is segmented by an intensity threshold on the texture image (optionally
also by its height over a first baseline); its polarity (darker or brighter than the
surroundings) is, unless given, the one whose segment stands above the surface. The segment
is then widened to, and cut down to, the pixels standing above half its median height (a
bright thread's obliquely lit flanks are dark, a dark thread's shading spills onto the
tissue). A smooth baseline surface (quadratic in the section coordinates) is fitted to a
ring of pixels around it (outside the depth map's blur skirt of the thread), and each
cross-section across the feature's long axis
is levelled by a quadratic through its two flanks (a caliper rests on both sides; the
quadratic follows the tissue's curvature under the thread). Cross-sections are taken in
pixel coordinates or, given the pixels' in-plane coordinates (``coords_mm``), across the
feature as it lies on the surface, free of the raised crest's parallax (seen obliquely over
sloping tissue, the crest's pixel is not where the tissue under it is imaged: image-space
sections are off by about slope·height·tan(view angle)). Then one crest
profile — a parabola across the feature about a straight crest axis,
h = H_i − k·(t − a − b·s)², one curvature and axis for all sections and a crest height per
section — is fitted by least squares to the central part of *all* cross-sections at once:
each H_i is linear in the data given the shared shape, so its expectation does not move with
the depth noise (the apex of a per-section parabola, c + b²/4|a|, is pushed up by
var(b)/4|a|; a maximum is pushed up by the noise itself). The height is the mean of the H_i
(one vote per section: per unit length). Its standard error comes from a block jackknife
over the cross-sections (neighbouring sections share blur and tissue, so blocks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from app.analysis.common import roi_mask

F64 = npt.NDArray[np.float64]
SQRT_2PI = math.sqrt(2.0 * math.pi)


@dataclass
class FeatureHeight:
    """Result of :func:`feature_height`.

    Attributes:
        height_mm: crest height of the profile fitted to all cross-sections (mean of the
            sections' crest heights), mm.
        height_std_mm: standard deviation of the per-section crest heights, mm (the spread a
            caliper would see along the feature).
        count: cross-sections measured.
        mask: (H, W) bool segmented feature pixels.
        crest_heights_mm: (count,) per cross-section crest heights H_i, mm: each section's
            mean of h + k·(t − axis)² with the shared profile (their mean is ``height_mm``).
        baseline_rms_mm: RMS residual of the baseline surface fit, mm.
        height_se_mm: standard error of ``height_mm``, mm (block jackknife over sections).
        polarity: ``"bright"`` or ``"dark"`` (as given, or as found).
        curvature_per_px2: k of the fitted profile, mm per squared unit of the section
            coordinates (px², or mm² with ``coords_mm``).
        blur: σ of the image blur measured across the thread's edges in the texture, in the
            section coordinates' unit (px, or mm with ``coords_mm``); ``height_mm`` includes
            the crest's restoration by k·σ².
    """

    height_mm: float
    height_std_mm: float
    count: int
    mask: npt.NDArray[np.bool_]
    crest_heights_mm: F64
    baseline_rms_mm: float
    height_se_mm: float = math.nan
    polarity: str = "bright"
    curvature_per_px2: float = math.nan
    blur: float = 0.0


@dataclass
class _Section:
    comp: int  # index of the connected segment
    s0: float  # position along the segment's axis, px
    t: F64  # across-axis coordinates (px) of the section's central pixels
    h: F64  # their heights over the flank line, mm


def feature_height(depth: npt.ArrayLike, texture: npt.ArrayLike, valid: npt.ArrayLike | None = None,
                   *, roi: tuple[int, int, int, int] | None = None, threshold: float | None = None,
                   polarity: str | None = None, height_threshold_mm: float | None = None,
                   ring_px: tuple[int, int] = (8, 24), min_area_px: int = 30,
                   min_section_px: int = 3, slab_px: float = 3.0, block_sections: int = 10,
                   coords_mm: npt.ArrayLike | None = None, flank_degree: int = 2) -> FeatureHeight:
    """Crest height of a feature over a fitted baseline (noise-unbiased, with its standard error).

    Args:
        depth: (H, W) float height map, mm, NaN invalid.
        texture: (H, W) intensity image (any numeric range) used for segmentation.
        valid: optional (H, W) bool mask (combined with finiteness of ``depth``).
        roi: (x0, y0, x1, y1) pixel box (x1, y1 exclusive) around the feature.
        threshold: intensity threshold; default Otsu's threshold inside the ROI.
        polarity: ``"bright"`` (feature brighter than surroundings), ``"dark"``, or None:
            found — the side of the threshold whose pixels stand higher above a baseline
            fitted to the whole ROI (a suture lies *on* the tissue).
        height_threshold_mm: if given, feature pixels must also stand this high above a
            first baseline fitted to the whole ROI.
        ring_px: (inner, outer) distance in pixels of the baseline ring from the feature; the
            inner gap keeps the flank fit out of the depth map's blur skirt around the thread
            (a quadratic flank fit bends up into it).
        min_area_px: connected segments smaller than this are ignored.
        min_section_px: cross-sections with fewer feature pixels are skipped.
        slab_px: half-length along the feature of the flank pixels used for each
            cross-section's local baseline line.
        block_sections: consecutive sections per jackknife block (≥ the blur's correlation length).
        coords_mm: optional (H, W, 2) in-plane coordinates of each pixel's surface point, mm
            (:func:`plane_coordinates` of the result's points and the reference-plane normal).
            The cross-sections are then taken in these metric coordinates, across the feature
            as it lies on the surface: seen obliquely, the raised crest's pixel looks at the
            tissue *beside* the point under the crest (parallax ≈ height·tan(view angle)), so on
            a sloping surface image-space sections read the height of the wrong base point.
            Sections are then one pixel pitch (the median spacing of neighbouring pixels) apart,
            and ``slab_px`` / ``ring_px`` stay in pixels (converted with that pitch where needed).
        flank_degree: degree (1 or 2) of each section's baseline through its two flanks: 2
            follows the tissue's curvature under the thread (used only where each flank has
            enough pixels; else 1).

    Returns:
        A :class:`FeatureHeight`.
    """
    z = np.asarray(depth, np.float64)
    tex = np.asarray(texture, np.float64)
    if z.ndim != 2:
        raise ValueError(f"depth: expected (H, W), got shape {z.shape}")
    if tex.shape != z.shape:
        raise ValueError(f"texture: shape {tex.shape} does not match depth {z.shape}")
    if polarity not in (None, "bright", "dark"):
        raise ValueError(f"polarity: must be 'bright', 'dark' or None (found), got {polarity!r}")
    inner, outer = (int(r) for r in ring_px)
    if not 0 <= inner < outer:
        raise ValueError(f"ring_px: need 0 <= inner < outer, got {ring_px}")
    if int(block_sections) != block_sections or block_sections < 1:
        raise ValueError(f"block_sections: need a positive integer, got {block_sections}")
    if flank_degree not in (1, 2):
        raise ValueError(f"flank_degree: must be 1 or 2, got {flank_degree!r}")
    coords = _pixel_coordinates(z.shape, coords_mm)
    area = roi_mask(z.shape, roi)
    ok = area & np.isfinite(z) & np.isfinite(tex) & np.isfinite(coords).all(axis=-1)
    if valid is not None:
        v = np.asarray(valid, bool)
        if v.shape != z.shape:
            raise ValueError(f"valid: shape {v.shape} does not match depth {z.shape}")
        ok &= v
    if ok.sum() < 50:
        raise ValueError(f"depth: only {int(ok.sum())} valid pixels in the ROI")
    if threshold is None:
        threshold = _otsu(tex[ok])
    # robust quadratic over the ROI: the surface the feature lies on
    first, _ = _fit_baseline(z, ok, coords)
    if polarity is None:
        polarity = _find_polarity(z - first, tex, ok, threshold)
    mask = area & ((tex > threshold) if polarity == "bright" else (tex < threshold))
    if height_threshold_mm is not None:
        mask &= (z - first) > height_threshold_mm
    labels, comps = _components(mask, min_area_px)
    if not comps:
        raise ValueError("threshold: no feature segment found in the ROI")
    labels = _grow_by_height(labels, comps, z - first, ok, outer)
    labels, raised = _trim_to_height(labels, comps, z - first, ok, min_area_px)
    mask = np.isin(labels, comps)
    near = cv2.dilate(mask.astype(np.uint8), _disk(inner)) > 0 if inner else mask
    far = cv2.dilate(mask.astype(np.uint8), _disk(outer)) > 0
    ring = far & ~near & ok & ~raised  # raised pixels are no ground for a caliper
    if ring.sum() < 20:
        raise ValueError("ring_px: too few valid baseline pixels around the feature")
    baseline, rms = _fit_baseline(z, ring, coords)
    resid = z - baseline
    # each segment's own flanks (its ring, by image distance: not a neighbour's, and not cut where
    # the thread hides the tissue right behind it, which metric coordinates would show as a gap)
    rings = [ring & (cv2.dilate((labels == c).astype(np.uint8), _disk(outer)) > 0) for c in comps]
    # The camera's blur mixes neighbouring pixels' fringes, so the depth map is blurred with the
    # same kernel as the texture: a crest h = H − k·t² blurred by a Gaussian of σ reads
    # H − k·σ², where its neighbourhood is thread alone (within 2σ of its edges the tissue, of
    # another albedo, weighs in). σ is measured on the thread's edges in the texture.
    edge = _edge_blur(tex, coords, labels, comps, far & np.isfinite(tex), area)
    blur = edge.sigma
    sections: list[_Section] = []
    for i, c in enumerate(comps):
        sections += _sections(resid, coords, (labels == c) & ok, rings[i], min_section_px, slab_px,
                              i, flank_degree, 2.0 * blur)
    if not sections:
        raise ValueError("depth: no cross-section of the feature has enough valid pixels")
    height, k, per_section, _, se, offsets = _joint_profile(sections, int(block_sections))
    # the crest, blurred as the texture is (see above), restored: for a parabola the drop is
    # k·σ²; a round thread's, with the tissue's weight near its edges, from its forward model
    fitted, drop = height, 0.0
    for _ in range(3):  # the drop depends (weakly) on the height it restores
        drop = _crest_drop(fitted + drop, offsets, edge, blur)
    drop_se = abs(_crest_drop(fitted + drop, offsets, edge, blur + edge.sigma_se) - drop)
    height = fitted + drop
    per_section = per_section + drop
    # The jackknife over sections cannot see the baseline surface's own error, common to all of
    # them where the flank lines do not absorb it (its curvature across the feature): add it,
    # propagated linearly through the same sections.
    basis, cov = _baseline_covariance(z, ring, baseline, rms, coords)
    effect = np.zeros(len(basis))
    for m, phi in enumerate(basis):
        moved: list[_Section] = []
        for i, c in enumerate(comps):
            moved += _sections(phi, coords, (labels == c) & ok, rings[i], min_section_px, slab_px,
                               i, flank_degree, 2.0 * blur)
        hm = np.concatenate([sec.h for sec in moved])
        effect[m] = -float(hm.mean())
    se = float(math.sqrt(se**2 + max(float(effect @ cov @ effect), 0.0) + drop_se**2)) \
        if math.isfinite(se) else se
    return FeatureHeight(
        height_mm=height,
        height_std_mm=float(per_section.std(ddof=1)) if len(per_section) > 1 else 0.0,
        count=len(per_section),
        mask=mask,
        crest_heights_mm=per_section,
        baseline_rms_mm=rms,
        height_se_mm=se,
        polarity=polarity,
        curvature_per_px2=k,
        blur=blur,
    )


def _grow_by_height(labels: npt.NDArray[np.int32], comps: list[int], resid: F64,
                    ok: npt.NDArray[np.bool_], reach_px: int) -> npt.NDArray[np.int32]:
    """Each segment widened, within ``reach_px``, to the pixels standing
    above half its median height.

    An intensity threshold can miss a round thread's flanks (a bright thread's sides are
    lit obliquely and darker than its top); left out, they would fall into the baseline ring
    and lift the baseline. A thread on a surface stands at least its radius — half its
    height — over it everywhere across its width, so half the median height of the segment
    catches its whole width.
    """
    sel = np.isin(labels, comps) & ok
    if not sel.any():
        return labels
    level = 0.5 * float(np.median(resid[sel]))
    if not level > 0:
        return labels
    raised = ok & ((resid > level) | (_local_mean(resid, ok) > level))
    out = labels.copy()
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for c in comps:
        grown = (labels == c).astype(np.uint8)
        for _ in range(reach_px):  # geodesic: one pixel a step, only through raised pixels
            step = (cv2.dilate(grown, cross) > 0) & raised & ((out == 0) | (out == c))
            if not (step & (grown == 0)).any():
                break
            grown[step] = 1
        out[(grown > 0) & (out == 0)] = c
    return out


def _trim_to_height(labels: npt.NDArray[np.int32], comps: list[int], resid: F64,
                    ok: npt.NDArray[np.bool_], min_area: int
                    ) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.bool_]]:
    """Each segment cut to its pixels standing above half its median height (a dark thread's
    rim of shading on the tissue beside it is dark but not raised), unless that leaves fewer
    than ``min_area`` pixels; also the (H, W) mask of all raised pixels (ground for no ring)."""
    sel = np.isin(labels, comps) & ok
    if not sel.any():
        return labels, np.zeros(labels.shape, bool)
    level = 0.5 * float(np.median(resid[sel]))
    if not level > 0:
        return labels, np.zeros(labels.shape, bool)
    raised = ok & ((resid > level) | (_local_mean(resid, ok) > level))
    out = labels.copy()
    for c in comps:
        seg = labels == c
        if int((seg & raised).sum()) >= min_area:
            out[seg & ~raised] = 0
    return out, raised


def _local_mean(resid: F64, ok: npt.NDArray[np.bool_], box: int = 5) -> F64:
    """Mean of ``resid`` over the valid pixels of each ``box``×``box`` neighbourhood (NaN: none).

    A pixel counts as raised if it or its neighbourhood stands above the level: judged by its own
    noisy height alone, the thread's pixels whose noise lowers them would be cut out and those it
    lifts kept (a crest read high).
    """
    m = ok.astype(np.float64)
    num = cv2.boxFilter(np.where(ok, resid, 0.0), -1, (box, box), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(m, -1, (box, box), normalize=False, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(den > 0, num / den, np.nan), np.float64)


def _find_polarity(resid: F64, tex: F64, ok: npt.NDArray[np.bool_], threshold: float) -> str:
    """``"bright"`` if the pixels above the threshold stand higher (median) over the ROI
    baseline than those below it, else ``"dark"``: the raised feature is the side of the
    threshold that stands up."""
    bright = ok & (tex > threshold)
    dark = ok & (tex < threshold)
    if not bright.any() or not dark.any():
        raise ValueError("threshold: splits nothing in the ROI, cannot tell the feature's polarity")
    return "bright" if float(np.median(resid[bright])) > float(np.median(resid[dark])) else "dark"


def plane_coordinates(points: npt.ArrayLike, normal: npt.ArrayLike) -> F64:
    """In-plane coordinates (mm) of camera-frame points on a plane with ``normal``.

    Args:
        points: (H, W, 3) camera-frame points, mm (NaN where invalid).
        normal: (3,) plane normal (e.g. the calibration's reference-plane normal).

    Returns:
        (H, W, 2) float64: the points' components along two orthonormal axes of the plane
        (the camera x axis made orthogonal to the normal, and normal × that), mm.
    """
    p = np.asarray(points, np.float64)
    n = np.asarray(normal, np.float64).ravel()
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"points: expected (H, W, 3), got shape {p.shape}")
    if n.shape != (3,) or not np.isfinite(n).all() or not np.linalg.norm(n) > 0:
        raise ValueError(f"normal: expected 3 finite numbers, not all zero, got {n.tolist()}")
    n = n / np.linalg.norm(n)
    e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0.0, 1.0, 0.0]) - n[1] * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([p @ e1, p @ e2], axis=-1)


def _pixel_coordinates(shape: tuple[int, ...], coords_mm: npt.ArrayLike | None) -> F64:
    """(H, W, 2) section coordinates: pixel (column, row), or the given metric ones."""
    if coords_mm is None:
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
        return np.stack([xx, yy], axis=-1)
    c = np.asarray(coords_mm, np.float64)
    if c.shape != (*shape, 2):
        raise ValueError(f"coords_mm: expected shape {(*shape, 2)}, got {c.shape}")
    return c


def _sections(resid: F64, coords: F64, seg: npt.NDArray[np.bool_], ring: npt.NDArray[np.bool_],
              min_px: int, slab_px: float, comp: int, flank_degree: int = 1,
              edge_margin: float = 0.0
              ) -> list[_Section]:
    """Cross-sections (one pixel pitch along the segment's long axis) levelled through both flanks.

    In each cross-section the baseline is refined by a polynomial of ``flank_degree`` (a line
    where a flank has too few pixels for more) through the ring pixels on both flanks (within
    ``slab_px`` along the axis), as a caliper rests on both sides; the central
    60 % of the section, chosen by position (not by value, which would favour upward noise),
    is kept — the part of a round thread a parabola describes well — and of it only what lies
    ``edge_margin`` (section units) or more inside the section's edges (where the blur mixes in
    the tissue), at least the central pixels.
    """
    ys, xs = np.nonzero(seg)
    if len(xs) < min_px:
        return []
    xy = coords[ys, xs]
    # one section per pixel pitch (1 in pixel coordinates; the median
    # neighbour spacing in metric ones)
    right = coords[ys, np.minimum(xs + 1, coords.shape[1] - 1)]
    step = float(np.nanmedian(np.linalg.norm(right - xy, axis=1)))
    if not step > 0:
        step = 1.0
    slab = slab_px * step
    centre = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - centre, full_matrices=False)
    along = (xy - centre) @ vt[0]
    across = (xy - centre) @ vt[1]
    r = resid[ys, xs]
    ry, rx = np.nonzero(ring)
    rxy = coords[ry, rx] - centre
    r_along, r_across, r_val = rxy @ vt[0], rxy @ vt[1], resid[ry, rx]
    r_order = np.argsort(r_along)
    r_along, r_across, r_val = r_along[r_order], r_across[r_order], r_val[r_order]
    section = np.rint(along / step).astype(np.int64)
    out: list[_Section] = []
    order = np.argsort(section, kind="stable")
    bounds = np.flatnonzero(np.diff(section[order])) + 1
    groups = [idx for idx in np.split(order, bounds) if len(idx) >= min_px]
    if not groups:
        return []
    # A thread's ends (cut, or diving into the tissue) are no crest: within about its width of
    # an end its height falls, and the blur drags it further along the thread. Sections closer
    # than the segment's median width (plus a pitch) to either end are left out.
    width = float(np.median([np.ptp(across[idx]) for idx in groups])) + step
    s_lo, s_hi = float(along.min()) + width, float(along.max()) - width
    for idx in groups:
        s0 = float(section[idx[0]]) * step
        if not s_lo <= s0 <= s_hi:
            continue
        lo, hi = np.searchsorted(r_along, [s0 - slab, s0 + slab])
        fa, fv = r_across[lo:hi], r_val[lo:hi]
        if (fa < across[idx].min()).sum() < 2 or (fa > across[idx].max()).sum() < 2:
            continue  # a caliper needs ground on both sides
        left, right = int((fa < across[idx].min()).sum()), int((fa > across[idx].max()).sum())
        deg = flank_degree if min(left, right) >= 3 * flank_degree else 1
        t, h = across[idx], r[idx] - np.polyval(np.polyfit(fa, fv, deg), across[idx])
        t_c, half = 0.5 * (t.max() + t.min()), 0.5 * float(np.ptp(t))
        reach = max(min(0.6 * half, half - edge_margin), 0.35 * half, 1.5 * step)
        top = np.abs(t - t_c) <= reach
        if top.sum() >= 3 and np.ptp(t[top]) > 0:
            out.append(_Section(comp, s0, t[top], h[top]))
    return out


@dataclass
class _Edge:
    """The thread's edges in the texture: blur σ and its standard error, half-width (section units)
    and the thread's brightness over the tissue's (the fringe amplitude ratio)."""

    sigma: float = 0.0
    sigma_se: float = 0.0
    half_width: float = math.nan
    albedo_ratio: float = 1.0


def _edge_blur(tex: F64, coords: F64, labels: npt.NDArray[np.int32], comps: list[int],
               region: npt.NDArray[np.bool_], area: npt.NDArray[np.bool_]) -> _Edge:
    """σ of the image blur across the thread (and its SE, the thread's half-width and brightness
    ratio), in the section coordinates.

    Per segment, the texture of the pixels around it (``region``, away from its ends) against
    their distance across its axis is fitted with a blurred band:
    A + g·t + (B − A)·[Φ((t − c₁)/σ) − Φ((t − c₂)/σ)] (tissue level A with a gradient g,
    thread level B, edges c₁ < c₂, Gaussian σ). The segments' figures are combined weighted by
    the inverse variances of their σ; σ = 0 (SE 0) where no fit converges (e.g. a thread wider
    than the region, or no contrast).

    Args:
        tex: (H, W) texture; coords: (H, W, 2) section coordinates; labels, comps: the segments.
        region: (H, W) bool pixels near the segments with a finite texture; area: the ROI.
    """
    from scipy.optimize import least_squares  # deferred: costs the live start-up CPU
    from scipy.special import ndtr

    estimates: list[tuple[float, float, float, float]] = []
    for c in comps:
        ys, xs = np.nonzero(labels == c)
        xy = coords[ys, xs]
        if len(xy) < 10 or not np.isfinite(xy).all():
            continue
        centre = xy.mean(axis=0)
        _, _, vt = np.linalg.svd(xy - centre, full_matrices=False)
        along, across = (xy - centre) @ vt[0], (xy - centre) @ vt[1]
        width = float(np.percentile(across, 98) - np.percentile(across, 2))
        near = region & area & (cv2.dilate((labels == c).astype(np.uint8), _disk(8)) > 0)
        ry, rx = np.nonzero(near)
        rxy = coords[ry, rx] - centre
        ra, rt, rv = rxy @ vt[0], rxy @ vt[1], tex[ry, rx]
        keep = (ra > along.min() + width) & (ra < along.max() - width)
        keep &= np.isfinite(rt) & np.isfinite(rv)
        ra, rt, rv = ra[keep], rt[keep], rv[keep]
        if len(rt) < 30 or not width > 0:
            continue
        outside = np.abs(rt - 0.5 * (across.min() + across.max())) > 0.5 * width + 0.25 * width
        inside = np.abs(rt - 0.5 * (across.min() + across.max())) < 0.25 * width
        if outside.sum() < 5 or inside.sum() < 5:
            continue
        a0, b0 = float(np.median(rv[outside])), float(np.median(rv[inside]))
        if not abs(b0 - a0) > 0:
            continue
        lo, hi = float(np.percentile(across, 2)), float(np.percentile(across, 98))

        def misfit(p: F64, t: F64 = rt, v: F64 = rv) -> F64:
            """Blurred band minus the texture: tissue A + g·t, thread B within c₁..c₂, blur σ."""
            band = ndtr((t - p[3]) / p[5]) - ndtr((t - p[4]) / p[5])
            return np.asarray(p[0] + p[1] * t + (p[2] - p[0]) * band - v, np.float64)

        def misfit_jac(p: F64, t: F64 = rt) -> F64:
            """(n, 6) exact derivatives of :func:`misfit` (finite differences cost 6 × more)."""
            z1, z2 = (t - p[3]) / p[5], (t - p[4]) / p[5]
            g1, g2 = np.exp(-0.5 * z1 * z1) / SQRT_2PI, np.exp(-0.5 * z2 * z2) / SQRT_2PI
            band = ndtr(z1) - ndtr(z2)
            step = (p[2] - p[0]) / p[5]
            return np.column_stack([1.0 - band, t, band, -step * g1, step * g2,
                                    step * (z2 * g2 - z1 * g1)])

        x0 = np.array([a0, 0.0, b0, lo, hi, 0.05 * width])
        lower = np.array([-np.inf, -np.inf, -np.inf, lo - width, lo, 1e-4 * width])
        upper = np.array([np.inf, np.inf, np.inf, hi, hi + width, width])
        try:
            fit = least_squares(misfit, np.clip(x0, lower + 1e-12, upper - 1e-12),
                                jac=misfit_jac, bounds=(lower, upper), method="trf",
                                x_scale="jac")
        except (ValueError, np.linalg.LinAlgError):
            continue
        dof = len(rv) - len(x0)
        s2 = float(np.sum(fit.fun**2)) / max(dof, 1)
        try:
            cov = s2 * np.linalg.inv(fit.jac.T @ fit.jac)
        except np.linalg.LinAlgError:
            continue
        var = float(cov[5, 5])
        if fit.success and var > 0 and math.isfinite(var) and fit.x[0] > 0 and fit.x[2] > 0:
            estimates.append((float(fit.x[5]), var, 0.5 * float(fit.x[4] - fit.x[3]),
                              float(fit.x[2] / fit.x[0])))
    if not estimates:
        return _Edge()
    e = np.array(estimates)
    w = 1.0 / e[:, 1]
    sigma = float(np.sum(w * e[:, 0]) / np.sum(w))
    # an edge sharper than half a pixel is unresolved: its fit's SE (a flat minimum) is no measure,
    # the blur lies within [0, half a pixel]
    ys, xs = np.nonzero(np.isin(labels, comps))
    right = coords[ys, np.minimum(xs + 1, coords.shape[1] - 1)]
    pitch = float(np.nanmedian(np.linalg.norm(right - coords[ys, xs], axis=1))) if len(xs) else 1.0
    se = min(float(math.sqrt(1.0 / np.sum(w))), max(sigma, 0.5 * pitch))
    half, ratio = (float(np.sum(w * e[:, j]) / np.sum(w)) for j in (2, 3))
    return _Edge(sigma, se, half, ratio)


def _crest_drop(height_mm: float, offsets: F64, edge: _Edge, sigma: float) -> float:
    """How much lower than a round thread's crest its blurred depth profile reads, mm, when fitted
    with a parabola at the section pixels' ``offsets`` from the crest axis (section units).

    The thread: a round cross-section of height ``height_mm`` and half-width ``edge.half_width``,
    brightness ``edge.albedo_ratio`` times the tissue's. The depth map: the camera's Gaussian blur
    ``sigma`` mixes the fringes, so each pixel's depth is the blur-weighted mean of its
    neighbours' depths, weighted by their fringe amplitude. The parabola fit of that profile at
    the offsets, against the true crest, gives the drop (the parabola-vs-circle difference with
    it: 0 blur still gives a small one).
    """
    r_u = edge.half_width
    if not (r_u > 0 and height_mm > 0 and offsets.size >= 3):
        return 0.0
    step = max(min(sigma, r_u) / 20.0, r_u / 2000.0)  # resolves the blur, bounded grid
    reach = r_u + 6.0 * sigma + float(np.max(np.abs(offsets)))
    d = np.arange(-reach, reach + step, step)
    inside = np.abs(d) < r_u
    radius = 0.5 * height_mm
    h = np.where(inside, radius * (1.0 + np.sqrt(np.clip(1.0 - (d / r_u) ** 2, 0.0, None))), 0.0)
    a = np.where(inside, edge.albedo_ratio, 1.0)
    if sigma > 0:
        from scipy.ndimage import gaussian_filter1d

        s_steps = sigma / step
        h = (gaussian_filter1d(a * h, s_steps, mode="nearest")
             / gaussian_filter1d(a, s_steps, mode="nearest"))
    obs = np.interp(offsets, d, h)
    design = np.column_stack([np.ones_like(offsets), -offsets * offsets])
    coef, *_ = np.linalg.lstsq(design, obs, rcond=None)
    return float(height_mm - coef[0])


def _joint_profile(sections: list[_Section], block: int
                   ) -> tuple[float, float, F64, F64, float, F64]:
    """Fit h = H_i − k·(t − a_c − b_c·s)² to every section's central pixels at once: one curvature
    k and one crest axis a_c + b_c·s per segment c shared by all sections, a crest height H_i per
    section i. H_i is eliminated in closed form (for a given shape it is the section's mean of
    h + k·d², linear in the data), so k is set by the curvature *within* sections only: the
    section-to-section wander of the tissue under the thread does not flatten it. H is the
    pixel-weighted mean of the H_i. 4σ (MAD) outliers are dropped once and the fit redone. The
    standard error of H is a delete-one-block jackknife (blocks of ``block`` consecutive sections
    in a segment), each block's fit redone, so the shape's own uncertainty counts.

    Returns (H, k, per-section heights (n,), their weights (n,) = pixels used, standard error of H,
    the used pixels' offsets from the crest axis (m,)).
    """
    comp = np.concatenate([np.full(len(s.t), s.comp) for s in sections])
    sec = np.concatenate([np.full(len(s.t), i) for i, s in enumerate(sections)])
    s_pos = np.concatenate([np.full(len(s.t), s.s0) for s in sections])
    t = np.concatenate([s.t for s in sections])
    h = np.concatenate([s.h for s in sections])
    n_sec = len(sections)
    n_comp = int(comp.max()) + 1
    s_ref = np.array([s_pos[comp == c].mean() if np.any(comp == c) else 0.0 for c in range(n_comp)])
    ds = s_pos - s_ref[comp]

    def lifted(x: F64) -> F64:
        """h + k·d²: each pixel's estimate of its section's crest height."""
        a, b = x[1 : 1 + n_comp], x[1 + n_comp :]
        d = t - a[comp] - b[comp] * ds
        return np.asarray(h + x[0] * d * d, np.float64)

    def section_means(values: F64, sel: npt.NDArray[np.bool_]) -> tuple[F64, F64]:
        w = np.bincount(sec[sel], minlength=n_sec).astype(np.float64)
        tot = np.bincount(sec[sel], weights=values[sel], minlength=n_sec)
        with np.errstate(invalid="ignore", divide="ignore"):
            return tot / w, w

    def residuals(x: F64, sel: npt.NDArray[np.bool_]) -> F64:
        lv = lifted(x)
        mean, _ = section_means(lv, sel)
        return np.asarray((lv - mean[sec])[sel], np.float64)

    # The crest axis stays among the sections' central pixels and the profile curves down: a
    # free axis far to one side with k → 0 would turn the parabola into a tilted line.
    t_lo = np.array([t[comp == c].min() if np.any(comp == c) else -1.0 for c in range(n_comp)])
    t_hi = np.array([t[comp == c].max() if np.any(comp == c) else 1.0 for c in range(n_comp)])
    lower = np.concatenate([[0.0], t_lo, np.full(n_comp, -0.5)])
    upper = np.concatenate([[np.inf], t_hi, np.full(n_comp, 0.5)])

    from scipy.optimize import least_squares  # deferred: costs the live start-up CPU

    def solve(x_start: F64, sel: npt.NDArray[np.bool_]) -> F64:
        x_start = np.clip(x_start, np.nextafter(lower, upper), np.nextafter(upper, lower))
        return np.asarray(least_squares(lambda p: residuals(p, sel), x_start, bounds=(lower, upper),
                                        method="trf", x_scale="jac").x)

    def height(x: F64, sel: npt.NDArray[np.bool_]) -> float:
        """Mean of the sections' crest heights, each section one vote: sections are spaced evenly
        along the feature, so this is its mean height per unit length (pixel weights would favour
        where the image happens to sample the surface densely)."""
        mean, w = section_means(lifted(x), sel)
        return float(mean[w > 0].mean())

    # start: a shared parabola in t about each segment's mean position, sections levelled
    a0 = np.array([t[comp == c].mean() if np.any(comp == c) else 0.0 for c in range(n_comp)])
    h_mean, _ = section_means(h, np.ones(len(h), bool))
    c2, _, _ = np.polyfit(t - a0[comp], h - h_mean[sec], 2)
    x = np.concatenate([[max(-c2, 1e-6)], a0, np.zeros(n_comp)])
    use = np.ones(len(h), bool)
    for _ in range(2):
        x = solve(x, use)
        lv = lifted(x)
        mean, _ = section_means(lv, use)
        e = lv - np.where(np.isfinite(mean), mean, np.nanmean(mean))[sec]
        sigma = 1.4826 * float(np.median(np.abs(e[use])))
        new = np.abs(e) <= max(4.0 * sigma, 1e-9)
        if np.array_equal(new, use) or new.sum() <= len(x) + n_sec:
            break
        use = new
    k = float(x[0])
    per, w = section_means(lifted(x), use)
    keep = w > 0
    # jackknife blocks: consecutive sections of one segment (sections are in order along each)
    sec_comp = np.array([s.comp for s in sections], np.int64)
    labels = np.zeros(n_sec, np.int64)
    nxt = 0
    for c in np.unique(sec_comp):
        idx = np.flatnonzero(sec_comp == c)
        labels[idx] = nxt + np.arange(len(idx)) // block
        nxt = int(labels[idx].max()) + 1
    se = math.nan
    if nxt >= 2:
        est = []
        for j in range(nxt):
            sel = use & (labels[sec] != j)
            est.append(height(solve(x, sel), sel))
        e_j = np.array(est)
        se = float(math.sqrt((nxt - 1) / nxt * np.sum((e_j - e_j.mean()) ** 2)))
    a_fit, b_fit = x[1 : 1 + n_comp], x[1 + n_comp :]
    offsets = (t - a_fit[comp] - b_fit[comp] * ds)[use]
    return height(x, use), k, per[keep], w[keep], se, np.asarray(offsets, np.float64)


def _quadratic_basis(coords: F64, sel: npt.NDArray[np.bool_]) -> F64:
    """(6, H, W) images 1, x, y, x², xy, y² of the section coordinates (pixel or in-plane), centred
    and scaled over the ``sel`` pixels (NaN where the coordinates are)."""
    c = coords[sel]
    centre = c.mean(axis=0)
    scale = max(float(np.ptp(c[:, 0])), float(np.ptp(c[:, 1])), 1e-12) / 2.0
    x, y = (coords[..., 0] - centre[0]) / scale, (coords[..., 1] - centre[1]) / scale
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y])


def _fit_baseline(z: F64, sel: npt.NDArray[np.bool_], coords: F64) -> tuple[F64, float]:
    """Quadratic surface in the section coordinates fitted to ``sel`` pixels with 3σ clipping;
    (H, W) and RMS. In the same coordinates as the sections: an image-space surface subtracted
    under metric sections would bring back the crest's parallax (its pixel is not
    above its base point)."""
    if int(sel.sum()) < 6:
        raise ValueError("depth: too few pixels for a baseline surface")
    basis = _quadratic_basis(coords, sel)
    a = basis[:, sel].T
    zz = z[sel]
    keep = np.ones(len(zz), bool)
    for _ in range(5):
        coef, *_ = np.linalg.lstsq(a[keep], zz[keep], rcond=None)
        e = zz - a @ coef
        sigma = 1.4826 * float(np.median(np.abs(e[keep])))
        new = np.abs(e) <= max(3 * sigma, 1e-9)
        if np.array_equal(new, keep):
            break
        keep = new
    return np.tensordot(coef, basis, axes=1), float(np.sqrt(np.mean(e[keep] ** 2)))


def _baseline_covariance(z: F64, sel: npt.NDArray[np.bool_], baseline: F64, rms: float,
                         coords: F64) -> tuple[F64, F64]:
    """Basis images (6, H, W) of :func:`_fit_baseline`'s quadratic and the covariance (6, 6) of its
    coefficients, rms²·(AᵀA)⁻¹ over the pixels it kept (|residual| ≤ 3·rms, as its clipping)."""
    basis = _quadratic_basis(coords, sel)
    with np.errstate(invalid="ignore"):
        kept = sel & (np.abs(z - baseline) <= 3.0 * max(rms, 1e-12))
    a = basis[:, kept].T
    factor = _correlation_factor(np.where(kept, z - baseline, 0.0), kept)
    cov = rms**2 * factor * np.linalg.pinv(a.T @ a)
    return basis, np.asarray(cov, np.float64)


def _correlation_factor(resid: F64, sel: npt.NDArray[np.bool_], box: int = 5) -> float:
    """How much spatial correlation inflates the variance of a mean over many pixels: the variance
    of ``box``×``box`` means over boxes wholly in ``sel``, times box², over the pixel variance (1
    for independent pixels; clipped to 1 … box²)."""
    m = sel.astype(np.float64)
    full = cv2.boxFilter(m, -1, (box, box), normalize=True,
                         borderType=cv2.BORDER_CONSTANT) > 1 - 1e-9
    if full.sum() < 10 or sel.sum() < 10:
        return 1.0
    means = cv2.boxFilter(resid * m, -1, (box, box), normalize=True,
                          borderType=cv2.BORDER_CONSTANT)[full]
    var = float(np.var(resid[sel]))
    if not var > 0:
        return 1.0
    return float(np.clip(np.var(means) * box * box / var, 1.0, box * box))


def _components(mask: npt.NDArray[np.bool_],
                min_area: int) -> tuple[npt.NDArray[np.int32], list[int]]:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_area]
    return np.asarray(labels, np.int32), keep


def _disk(r: int) -> npt.NDArray[np.uint8]:
    return np.asarray(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)),
                      np.uint8)


def _otsu(values: F64) -> float:
    lo, hi = float(values.min()), float(values.max())
    if not hi > lo:
        raise ValueError("texture: constant in the ROI, nothing to segment")
    scaled = np.clip((values - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8).reshape(-1, 1)
    t, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return lo + (float(t) + 0.5) / 255.0 * (hi - lo)


__all__ = ["FeatureHeight", "feature_height", "plane_coordinates"]
