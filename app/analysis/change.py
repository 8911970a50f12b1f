"""The change map when the scope may have moved: rigid registration, then change along the normal.

A fixed scope compares pixel by pixel (:func:`app.recon.change.change_map`). When most of the
compared surface "changed" (``moved_share``, default one half) the scope itself moved (or the
whole scene did: breathing): the current cloud is registered rigidly to the reference cloud by
point-to-plane ICP (small_gicp: a 0.4 MB wheel against Open3D's 105 MB, and built for speed),
coarse to fine, and the change is measured along the reference surface's normal:

    ``Δ = (R·p + t − p_ref) · n_ref``  (mm, positive toward the scope)

for each reference pixel and the current point that projects into it (the nearest to the
camera where several do). ``σ_Δ = √(σ² + σ_ref²)`` with each map's sensor-noise σ, and the
changed test is the fixed scope's; with the maps' calibration 1-σ (σ_model) given, the paired
pixels' calibration errors, which no longer cancel, enter as an error shared by neighbouring
pixels (:func:`app.recon.change.change_with_shared_error`). A registration whose matched share
or residual fails its bounds says so (``mode == "failed"``) and shows no change rather than
change everywhere.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Literal, NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from app.recon.change import (
    ChangeMap,
    ChangeTest,
    change_from_delta,
    change_map,
    change_with_shared_error,
)

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: a fixed-scope map with more than this share of changed pixels is registered first
DEFAULT_MOVED_SHARE = 0.5
#: voxel size of the clouds the ICP aligns, mm
DEFAULT_VOXEL_MM = 0.5
#: correspondence distances of the coarse and the fine ICP passes, mm
COARSE_DISTANCE_MM = 5.0
FINE_DISTANCE_MM = 1.0
#: a registration is trusted when at least this share of the current cloud matched...
DEFAULT_MIN_OVERLAP = 0.5
#: ...with an RMS point-to-plane residual of at most this, mm
DEFAULT_MAX_RESIDUAL_MM = 0.25

Mode = Literal["fixed", "registered", "failed"]
RegisterPolicy = Literal["auto", "never", "always"]


@dataclass(frozen=True)
class Registration:
    """A rigid registration of the current cloud to the reference cloud.

    Attributes:
        ok: whether it is trusted (matched share and residual within bounds, ICP converged).
        transform: (4, 4) float64, current camera frame → reference camera frame (mm).
        residual_mm: RMS point-to-plane distance after alignment, mm: of the matched voxel
            points from :func:`register_rigid`; of every unchanged pixel pair once
            :func:`compare` refined it.
        overlap: share of the current voxel points matched within the fine distance.
        iterations: ICP iterations of the fine pass.
        elapsed_ms: wall time, ms.
        note: why it is not trusted ("" when ok).
    """

    ok: bool
    transform: F64
    residual_mm: float
    overlap: float
    iterations: int
    elapsed_ms: float
    note: str = ""

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation part, degrees."""
        c = (float(np.trace(self.transform[:3, :3])) - 1.0) / 2.0
        return math.degrees(math.acos(min(1.0, max(-1.0, c))))

    @property
    def translation_mm(self) -> float:
        """Length of the translation part, mm."""
        return float(np.linalg.norm(self.transform[:3, 3]))


@dataclass(frozen=True)
class ChangeResult:
    """One comparison against the reference.

    Attributes:
        cmap: the change map (all NaN and unchanged when ``mode == "failed"``).
        mode: ``"fixed"`` (pixel by pixel), ``"registered"`` (after a rigid registration,
            along the reference normal) or ``"failed"`` (the scene moved and the registration
            failed: no change shown).
        registration: the registration when one was tried.
        fixed_changed_share: the changed share of the pixel-by-pixel map (what decided it).
        elapsed_ms: wall time of the whole comparison, ms.
    """

    cmap: ChangeMap
    mode: Mode
    registration: Registration | None = None
    fixed_changed_share: float = 0.0
    elapsed_ms: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)


def _cloud(points: F32) -> F64:
    """(N, 3) float64 finite points of an (H, W, 3) map."""
    flat = points.reshape(-1, 3)
    out: F64 = flat[np.isfinite(flat).all(axis=1)].astype(np.float64)
    return out


#: a transform that one more ICP step moves by less than this has settled (rad, mm): far below
#: the noise of a map's points (tens of µm), which the pixel-pair refinement then works at
SETTLED_ROTATION_RAD = 1e-5
SETTLED_TRANSLATION_MM = 1e-3


def register_rigid(points: F32, ref_points: F32, *, voxel_mm: float = DEFAULT_VOXEL_MM,
                   min_overlap: float = DEFAULT_MIN_OVERLAP,
                   max_residual_mm: float = DEFAULT_MAX_RESIDUAL_MM) -> Registration:
    """Point-to-plane ICP of ``points`` onto ``ref_points`` (small_gicp), coarse then fine.

    Args:
        points, ref_points: (H, W, 3) float32 camera-frame points, mm, NaN invalid.
        voxel_mm: voxel size both clouds are thinned to, mm (> 0).
        min_overlap: least share of the current voxel points matched within
            :data:`FINE_DISTANCE_MM` for a trusted result, (0, 1].
        max_residual_mm: largest RMS point-to-plane residual of a trusted result, mm.

    Returns:
        a :class:`Registration` (``ok`` False with a ``note`` when not trusted).
    """
    import small_gicp  # lazily: only the registered case needs it

    t0 = time.perf_counter()
    for name, arr in (("points", points), ("ref_points", ref_points)):
        if not isinstance(arr, np.ndarray) or arr.ndim != 3 or arr.shape[2] != 3:
            raise ValueError(f"{name}: expected (H, W, 3), got {getattr(arr, 'shape', None)}")
    if not (math.isfinite(voxel_mm) and voxel_mm > 0):
        raise ValueError(f"voxel_mm: must be > 0, got {voxel_mm}")
    if not 0 < min_overlap <= 1:
        raise ValueError(f"min_overlap: must be in (0, 1], got {min_overlap}")
    src, dst = _cloud(points), _cloud(ref_points)
    ident = np.eye(4)
    if len(src) < 100 or len(dst) < 100:
        return Registration(False, ident, math.nan, 0.0, 0, _ms(t0),
                            f"too few valid points to register ({len(src)} now, "
                            f"{len(dst)} in the reference)")
    target, target_tree = small_gicp.preprocess_points(dst, downsampling_resolution=voxel_mm,
                                                       num_neighbors=20)
    source, source_tree = small_gicp.preprocess_points(src, downsampling_resolution=voxel_mm,
                                                       num_neighbors=20)
    del source_tree
    if target.size() < 100 or source.size() < 100:  # e.g. a cloud collapsed to a point
        return Registration(False, ident, math.nan, 0.0, 0, _ms(t0),
                            f"too few distinct points to register ({source.size()} voxels "
                            f"now, {target.size()} in the reference)")
    transform = ident
    iterations = 0
    converged = False
    for dist in (COARSE_DISTANCE_MM, FINE_DISTANCE_MM):
        # convergence far below the defaults (0.1°, 1 µm): a 0.01° tilt is 7 µm at 40 mm
        res = small_gicp.align(target, source, target_tree, transform,
                               registration_type="PLANE_ICP",
                               max_correspondence_distance=dist, max_iterations=100,
                               rotation_epsilon=1e-6, translation_epsilon=1e-5)
        transform = np.asarray(res.T_target_source, np.float64)
        iterations, converged = int(res.iterations), bool(res.converged)
    if not converged:
        # the epsilons above sit at the noise's own jitter of the solution: one more step that
        # moves it by far less than the noise (and the pixel-pair refinement that follows)
        # is convergence too
        step = small_gicp.align(target, source, target_tree, transform,
                                registration_type="PLANE_ICP",
                                max_correspondence_distance=FINE_DISTANCE_MM, max_iterations=1)
        moved = np.asarray(step.T_target_source, np.float64) @ np.linalg.inv(transform)
        cos_angle = (np.trace(moved[:3, :3]) - 1.0) / 2.0
        angle_rad = math.acos(min(1.0, max(-1.0, cos_angle)))
        converged = angle_rad <= SETTLED_ROTATION_RAD and \
            float(np.linalg.norm(moved[:3, 3])) <= SETTLED_TRANSLATION_MM
    residual, overlap = _residual(np.asarray(source.points())[:, :3],
                                  np.asarray(target.points())[:, :3],
                                  np.asarray(target.normals())[:, :3], target_tree, transform)
    note = ""
    if not converged:
        note = "registration did not converge"
    elif overlap < min_overlap:
        note = (f"registration matched only {overlap:.0%} of the surface "
                f"(needs {min_overlap:.0%})")
    elif not residual <= max_residual_mm:
        note = (f"registration residual {residual:.3f} mm exceeds {max_residual_mm:.3f} mm")
    return Registration(note == "", transform, residual, overlap, iterations, _ms(t0), note)


def _residual(src: F64, dst: F64, normals: F64, tree: object, transform: F64
              ) -> tuple[float, float]:
    """(RMS point-to-plane distance of matched points, matched share) after ``transform``."""
    moved = src @ transform[:3, :3].T + transform[:3, 3]
    found, sq = tree.batch_nearest_neighbor_search(moved)  # type: ignore[attr-defined]
    idx = np.asarray(found, np.int64).reshape(-1)
    ok = (idx >= 0) & (np.asarray(sq).reshape(-1) <= FINE_DISTANCE_MM**2)
    if not ok.any():
        return math.nan, 0.0
    d = np.einsum("ij,ij->i", moved[ok] - dst[idx[ok]], normals[idx[ok]])
    return float(np.sqrt(np.mean(d * d))), float(ok.mean())


def _ms(t0: float) -> float:
    return 1000.0 * (time.perf_counter() - t0)


def surface_normals(points: F32, step_px: int = 2) -> F32:
    """(H, W, 3) float32 unit normals of an organised cloud, pointing toward the camera.

    Args:
        points: (H, W, 3) float32 camera-frame points, mm, NaN invalid.
        step_px: half-width of the central differences, px (≥ 1; larger is smoother).

    Returns:
        normals from ``(P[u+k] − P[u−k]) × (P[v+k] − P[v−k])``, NaN where a neighbour is
        invalid or outside the image.
    """
    if int(step_px) != step_px or step_px < 1:
        raise ValueError(f"step_px: must be an integer >= 1, got {step_px}")
    k = int(step_px)
    h, w = points.shape[:2]
    du = np.full(points.shape, np.nan, np.float32)
    dv = np.full(points.shape, np.nan, np.float32)
    du[:, k:w - k] = points[:, 2 * k:] - points[:, :w - 2 * k]
    dv[k:h - k] = points[2 * k:] - points[:h - 2 * k]
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    flip = np.einsum("ijk,ijk->ij", n, points) > 0  # toward the camera: n · P < 0
    n[flip] *= -1
    out: F32 = n.astype(np.float32, copy=False)
    return out


class _Pairs(NamedTuple):
    """Reference pixels ``hit`` (flat indices) and the moved current points that project into
    them, with their flat indices ``src`` in the current map."""

    hit: npt.NDArray[np.int64]
    src: npt.NDArray[np.int64]
    moved: F64


def project_to_pixels(points: F64, camera_matrix: F64, dist_coeffs: F64) -> F64:
    """Pixel coordinates of camera-frame points: ``cv2.projectPoints`` with rvec = tvec = 0.

    The same arithmetic in the same order as OpenCV's (bit-identical results, checked in
    tests/analysis/test_change_registration.py) without the (2N, 15) Jacobian its Python
    binding always computes: for a whole map (1.4 M points) that is 336 MB and ~6x the time.
    A tilted sensor (14 coefficients, τx or τy ≠ 0) goes to OpenCV.

    Args:
        points: (N, 3) float64 camera-frame points, mm (z = 0 is taken as z = 1, as OpenCV).
        camera_matrix: (3, 3) intrinsics, px (the skew is ignored, as OpenCV).
        dist_coeffs: OpenCV distortion coefficients (0, 4, 5, 8, 12 or 14 of them).

    Returns:
        (N, 2) float64 pixel coordinates (u, v).
    """
    dist = np.asarray(dist_coeffs, np.float64).ravel()
    if dist.size > 12 and np.any(dist[12:] != 0):
        uv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera_matrix, dist)
        out: F64 = np.asarray(uv, np.float64).reshape(-1, 2)
        return out
    k = np.zeros(12)
    k[:dist.size] = dist[:12]
    z = points[:, 2]
    inv_z = np.where(z != 0, 1.0 / np.where(z != 0, z, 1.0), 1.0)
    x, y = points[:, 0] * inv_z, points[:, 1] * inv_z
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a1, a2, a3 = 2 * x * y, r2 + 2 * x * x, r2 + 2 * y * y
    radial = 1 + k[0] * r2 + k[1] * r4 + k[4] * r6
    inv_rational = 1.0 / (1 + k[5] * r2 + k[6] * r4 + k[7] * r6)
    # term by term in OpenCV's order: the sums round as its do
    xd = x * radial * inv_rational + k[2] * a1 + k[3] * a2 + k[8] * r2 + k[9] * r4
    yd = y * radial * inv_rational + k[2] * a3 + k[3] * a1 + k[10] * r2 + k[11] * r4
    uv_px: F64 = np.empty((len(points), 2))
    uv_px[:, 0] = xd * camera_matrix[0, 0] + camera_matrix[0, 2]
    uv_px[:, 1] = yd * camera_matrix[1, 1] + camera_matrix[1, 2]
    return uv_px


def _pairs(points: F32, valid: npt.NDArray[np.bool_], transform: F64, shape: tuple[int, int],
           camera_matrix: F64, dist_coeffs: F64, stride: int = 1) -> _Pairs:
    h, w = shape
    flat = points.reshape(-1, 3)
    if stride > 1:  # every stride-th row and column of the current map only
        thin = np.zeros_like(valid)
        thin[::stride, ::stride] = valid[::stride, ::stride]
        valid = thin
    keep = np.flatnonzero(valid.reshape(-1))
    moved = flat[keep].astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
    front = moved[:, 2] > 0
    keep, moved = keep[front], moved[front]
    if len(keep) == 0:  # nothing in front of the camera (cv2 returns None for no points)
        return _Pairs(keep, keep, moved)
    uv = np.rint(project_to_pixels(moved, camera_matrix, dist_coeffs)).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    keep, moved, uv = keep[inside], moved[inside], uv[inside]
    # the point nearest the camera wins a pixel: written last
    order = np.argsort(-moved[:, 2], kind="stable")
    slot = np.full(h * w, -1, np.int64)
    slot[uv[order, 1] * w + uv[order, 0]] = order
    # where the moved view is magnified some pixels get no point: they take a neighbour's (a
    # tangential offset of a pixel changes nothing along the normal to first order)
    grid = slot.reshape(h, w)
    for dv, du in (() if stride > 1 else ((0, 1), (0, -1), (1, 0), (-1, 0))):
        empty = grid < 0
        src = np.full_like(grid, -1)  # src[v, u] = grid[v − dv, u − du], no wrap-around
        src[max(dv, 0):h + min(dv, 0), max(du, 0):w + min(du, 0)] = \
            grid[max(-dv, 0):h - max(dv, 0), max(-du, 0):w - max(du, 0)]
        grid[empty] = src[empty]
    hit = np.flatnonzero(slot >= 0)
    j = slot[hit]
    return _Pairs(hit, keep[j], moved[j])


def refine_on_pixels(points: F32, sigma: F32, ref_points: F32, ref_sigma: F32,
                     transform: F64, camera_matrix: F64, dist_coeffs: F64,
                     iterations: int = 3) -> F64:
    """Refine a registration on every pixel pair (point-to-plane Gauss–Newton steps).

    The ICP aligns voxel-thinned clouds; here each reference pixel is paired with the moved
    current point that projects into it, and ``Σ ((R q + t − p) · n)² / σ_Δ²`` is minimised
    over the pairs within 3 σ_Δ (a local change does not pull the fit).

    Args:
        (as :func:`change_along_normal`); iterations: Gauss–Newton steps (≥ 1).

    Returns:
        the refined (4, 4) transform.
    """
    h, w = ref_points.shape[:2]
    valid = np.isfinite(points).all(axis=2) & np.isfinite(sigma)
    normals = surface_normals(ref_points).reshape(-1, 3).astype(np.float64)
    ref_flat = ref_points.reshape(-1, 3).astype(np.float64)
    out = transform.copy()
    for _ in range(iterations):
        # a quarter of the pairs (every 2nd row and column) fix six parameters as well
        pr = _pairs(points, valid, out, (h, w), camera_matrix, dist_coeffs, stride=2)
        n = normals[pr.hit]
        r = np.einsum("ij,ij->i", pr.moved - ref_flat[pr.hit], n)
        s2 = sigma.reshape(-1)[pr.src] ** 2 + ref_sigma.reshape(-1)[pr.hit] ** 2
        use = np.isfinite(r) & np.isfinite(n).all(axis=1) & np.isfinite(s2) & (r * r < 9 * s2)
        if use.sum() < 100:
            break
        jac = np.hstack([np.cross(pr.moved[use], n[use]), n[use]])  # d r / d(ω, δt)
        wt = 1.0 / s2[use]
        step = np.linalg.solve(jac.T @ (jac * wt[:, None]), -(jac.T @ (r[use] * wt)))
        rot = cv2.Rodrigues(step[:3])[0]
        upd = np.eye(4)
        upd[:3, :3] = rot
        upd[:3, 3] = step[3:]
        out = upd @ out
    return out


def change_along_normal(points: F32, sigma: F32, ref_points: F32, ref_sigma: F32,
                        transform: F64, camera_matrix: F64, dist_coeffs: F64, *,
                        test: ChangeTest | None = None, sigma_model: F32 | None = None,
                        ref_sigma_model: F32 | None = None) -> ChangeMap:
    """The change map on the reference's pixel grid after moving the current cloud.

    Args:
        points, sigma: current (H, W, 3) points and (H, W) depth σ, mm, NaN invalid.
        ref_points, ref_sigma: the reference's.
        transform: (4, 4) current → reference camera frame (:class:`Registration`).
        camera_matrix, dist_coeffs: the camera's intrinsics (the calibration's).
        test: the changed-pixel test.
        sigma_model, ref_sigma_model: (H, W) the calibration's own 1-σ of each map (σ_model),
            mm, or None (0). The paired pixels see the surface through other parts of the
            calibration, so its errors no longer cancel: their difference, 1-σ
            ``√(σ_model² + σ_model,ref²)``, enters as an error shared by neighbouring pixels
            (:func:`~app.recon.change.change_with_shared_error`), not as independent noise.

    Returns:
        a :class:`~app.recon.change.ChangeMap` with Δ along the reference normal and σ_Δ
        including :func:`registered_extra_sigma_mm` (and the calibrations' part).
    """
    t0 = time.perf_counter()
    h, w = ref_points.shape[:2]
    if points.shape != ref_points.shape or sigma.shape != (h, w) or ref_sigma.shape != (h, w):
        raise ValueError(f"points: shapes differ from the reference's {ref_points.shape}")
    valid = np.isfinite(points).all(axis=2) & np.isfinite(sigma)
    pr = _pairs(points, valid, transform, (h, w), camera_matrix, dist_coeffs)
    normals = surface_normals(ref_points).reshape(-1, 3)
    ref_flat = ref_points.reshape(-1, 3)
    delta = np.full(h * w, np.nan, np.float32)
    sig = np.full(h * w, np.nan, np.float32)
    delta[pr.hit] = np.einsum("ij,ij->i", pr.moved - ref_flat[pr.hit], normals[pr.hit])
    sig[pr.hit] = np.hypot(sigma.reshape(-1)[pr.src], ref_sigma.reshape(-1)[pr.hit])
    extra = registered_extra_sigma_mm(delta.reshape(h, w))
    if extra > 0:
        sig[pr.hit] = np.hypot(sig[pr.hit], np.float32(extra))
    if sigma_model is None and ref_sigma_model is None:
        cm = change_from_delta(delta.reshape(h, w), sig.reshape(h, w), test=test)
    else:
        shared = np.zeros(h * w, np.float32)
        for name, arr, idx in (("sigma_model", sigma_model, pr.src),
                               ("ref_sigma_model", ref_sigma_model, pr.hit)):
            if arr is None:
                continue
            if arr.shape != (h, w):
                raise ValueError(f"{name}: shape {arr.shape} differs from {(h, w)}")
            part = np.nan_to_num(arr.reshape(-1)[idx].astype(np.float32), nan=0.0)
            shared[pr.hit] = np.hypot(shared[pr.hit], part)
        cm = change_with_shared_error(delta.reshape(h, w), sig.reshape(h, w),
                                      shared.reshape(h, w), test=test)
    return ChangeMap(cm.delta, cm.sigma, cm.changed, cm.compared, cm.test, _ms(t0))


def registered_extra_sigma_mm(delta: F32, smooth_px: float = 8.0) -> float:
    """The 1-σ of what a registered comparison adds to the two maps' noise, mm.

    After the scope moved a surface point is seen through other pixels, so the calibration's
    smooth systematic error no longer cancels, and the registration leaves a small error of
    its own: both are smooth across the image, which the pooled window test would read as
    change. Their size is measured on Δ smoothed by a Gaussian of ``smooth_px`` (the noise
    averages out): 1.4826 × its median absolute deviation (robust: most of the surface did
    not change).

    Args:
        delta: (H, W) Δ along the reference normal, mm, NaN where not compared.
        smooth_px: σ of the Gaussian, px (> 0).

    Returns:
        the spread, mm (0 without data).
    """
    if not smooth_px > 0:
        raise ValueError(f"smooth_px: must be > 0, got {smooth_px}")
    ok = np.isfinite(delta)
    if not ok.any():
        return 0.0
    num = cv2.GaussianBlur(np.where(ok, delta, 0.0).astype(np.float32), (0, 0), smooth_px)
    den = cv2.GaussianBlur(ok.astype(np.float32), (0, 0), smooth_px)
    smooth = num[ok] / np.maximum(den[ok], 1e-6)
    med = float(np.median(smooth))
    return 1.4826 * float(np.median(np.abs(smooth - med)))


def _failed_map(shape: tuple[int, int], test: ChangeTest) -> ChangeMap:
    nan = np.full(shape, np.nan, np.float32)
    return ChangeMap(nan, nan.copy(), np.zeros(shape, np.bool_), 0, test)


def compare(depth: F32, sigma: F32, points: F32, ref_depth: F32, ref_sigma: F32,
            ref_points: F32, *, camera_matrix: F64, dist_coeffs: F64,
            test: ChangeTest | None = None, register: RegisterPolicy = "auto",
            moved_share: float = DEFAULT_MOVED_SHARE, sigma_model: F32 | None = None,
            ref_sigma_model: F32 | None = None) -> ChangeResult:
    """The change of the current map against the reference, registering when the scope moved.

    Args:
        depth, sigma, points: the current map's (H, W) height and σ and (H, W, 3) points, mm.
        ref_depth, ref_sigma, ref_points: the reference's.
        camera_matrix, dist_coeffs: the calibration's intrinsics (for the registered case).
        test: the changed-pixel test.
        register: ``"auto"`` (register when more than ``moved_share`` of the compared pixels
            changed), ``"never"`` (fixed scope) or ``"always"``.
        moved_share: see ``register``, in (0, 1].
        sigma_model, ref_sigma_model: each map's calibration 1-σ (σ_model), mm, or None: used
            once registered (:func:`change_along_normal`); a fixed scope's cancel.

    Returns:
        a :class:`ChangeResult`.
    """
    t0 = time.perf_counter()
    test = ChangeTest() if test is None else test
    if register not in ("auto", "never", "always"):
        raise ValueError(f"register: must be auto, never or always, got {register!r}")
    if not 0 < moved_share <= 1:
        raise ValueError(f"moved_share: must be in (0, 1], got {moved_share}")
    fixed = change_map(depth, sigma, ref_depth, ref_sigma, test=test)
    share = fixed.changed_share
    if register == "never" or (register == "auto" and share <= moved_share):
        return ChangeResult(fixed, "fixed", None, share, _ms(t0))
    reg = register_rigid(points, ref_points)
    if not reg.ok:
        return ChangeResult(_failed_map(depth.shape, test), "failed", reg, share, _ms(t0),
                            (reg.note,))
    fine = refine_on_pixels(points, sigma, ref_points, ref_sigma, reg.transform,
                            camera_matrix, dist_coeffs)
    cm = change_along_normal(points, sigma, ref_points, ref_sigma, fine,
                             camera_matrix, dist_coeffs, test=test, sigma_model=sigma_model,
                             ref_sigma_model=ref_sigma_model)
    # the residual of the final transform: the unchanged surface's RMS Δ along the normal
    still = ~cm.changed & np.isfinite(cm.delta)
    residual = float(np.sqrt(np.mean(np.square(cm.delta[still], dtype=np.float64))))
    reg = replace(reg, transform=fine, residual_mm=residual, elapsed_ms=_ms(t0))
    return ChangeResult(cm, "registered", reg, share, _ms(t0))


__all__ = ["DEFAULT_MOVED_SHARE", "ChangeResult", "Registration", "change_along_normal",
           "compare", "project_to_pixels", "register_rigid", "registered_extra_sigma_mm",
           "surface_normals"]
