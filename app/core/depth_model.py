"""The depth-model contract: unwrapped phase → height above the reference plane, per pixel.

Every model maps the finest-frequency unwrapped phase φ (rad) at pixel (u, v) to a height
in one closed form that the fused kernel evaluates:

    φ' = (φ − phi0)·inv_sphi,   t = φ' + cubic·φ'³
    height = (a0 + a1·t) / (b0 + b1·t)

where each of a0, a1, b0, b1 is a per-row quadratic in the normalised column u' plus a
linear form in the pixel's ray quotient ``q = r/(n·r)`` (``r = (x, y, 1)`` the undistorted
camera ray, ``n`` the reference-plane normal):

    a_i = α_i(v) + β_i(v)·u' + γ_i(v)·u'² + ρ_i·q_x + σ_i·q_y + τ_i·q_z

Eq. (5) uses the row quadratics only (``cubic`` 0); the geometric model the ray terms
only. :class:`HeightTables` carries both parts; a model says which by its numbers.

A radial projector lens (``radial_k`` ≠ 0, then ``cubic`` is 0) bends each fringe along its
length: ``φ' = t·(1 + radial_k·(t² + y²))`` with y the undistorted projector coordinate across
the fringes, which along the pixel's ray moves on its epipolar line ``y = α + β·t``, with
``α = e0·q / d·q`` and ``β = e1·q / d·q`` (``cross_coefs`` = e0, e1, d): a cubic in t per pixel
that :func:`column_term` solves by Newton's method.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

@dataclass(frozen=True)
class ReferencePlane:
    """``normal · X + offset_mm = height`` in the camera frame; normal toward the scope."""

    normal: F64
    offset_mm: float


class HeightTables(NamedTuple):
    """The closed form of the module docstring for one image size (float64; the kernel casts).

    Attributes:
        u_norm: (W,) normalised column u'.
        row_coefs: (H, 12) (α, β, γ) of a0, a1, b0, b1 per row.
        ray_coefs: (12,) (ρ, σ, τ) of a0, a1, b0, b1 on the ray quotient q.
        phi0, inv_sphi: phase normalisation.
        cubic: coefficient of φ'³ in t.
        cross_coefs: (9,) e0, e1, d (3 each) on the ray quotient q: the pixel's epipolar line.
        radial_k: the radial lens's coefficient (0: none).
    """

    u_norm: F64
    row_coefs: F64
    ray_coefs: F64
    phi0: float
    inv_sphi: float
    cubic: float
    cross_coefs: F64
    radial_k: float


#: Newton steps of :func:`column_term` from its first-order start (2 reach 1e-12 of the
#: coordinate at radial_k 0.05; the third covers the random rigs' 0.2)
COLUMN_ITERATIONS = 3


def epipolar_lines(cross_coefs: npt.ArrayLike, ray_q: npt.ArrayLike) -> tuple[F64, F64]:
    """(α, β), each of shape (…), of the epipolar lines ``y = α + β·t`` of rays ``ray_q`` (…, 3)
    (any scale: the ratios cancel it) under :attr:`HeightTables.cross_coefs` (9,)."""
    c = np.asarray(cross_coefs, np.float64).reshape(3, 3)
    q = np.asarray(ray_q, np.float64)
    if q.shape[-1:] != (3,):
        raise ValueError(f"ray_q: need shape (..., 3), got {q.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_d = 1.0 / (q @ c[2])
        return np.asarray((q @ c[0]) * inv_d), np.asarray((q @ c[1]) * inv_d)


def column_term(pp: npt.ArrayLike, cubic: float, alpha: npt.ArrayLike, beta: npt.ArrayLike,
                radial_k: float, iterations: int = COLUMN_ITERATIONS) -> tuple[F64, F64]:
    """(t, dt/dφ') of the module docstring: the undistorted projector coordinate t along the
    fringe axis (…) of the distorted one ``pp`` = φ' (…), with ``radial_k`` on the epipolar lines
    (α, β) (…); ``radial_k`` 0: ``φ' + cubic·φ'³`` and ``1 + 3·cubic·φ'²``."""
    x = np.asarray(pp, np.float64)
    if radial_k == 0.0:
        return x + cubic * x**3, 1.0 + 3.0 * cubic * x * x
    a, b = np.asarray(alpha, np.float64), np.asarray(beta, np.float64)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        y = a + b * x
        t = x * (1.0 - radial_k * (x * x + y * y))  # the first-order inverse
        inv = np.ones_like(x)
        for _ in range(iterations):
            y = a + b * t
            inv = 1.0 / (1.0 + radial_k * (3.0 * t * t + y * y + 2.0 * t * b * y))
            t = t - (t * (1.0 + radial_k * (t * t + y * y)) - x) * inv
        return t, inv


@dataclass
class BoardSamples:
    """Phase control points from the calibration boards (all (n,) unless noted).

    Attributes:
        u, v: pixel coordinates (column, row).
        ray_xy: (n, 2) undistorted normalised camera ray (x, y) of each point (z = 1).
        phi: finest-frequency unwrapped phase, rad.
        z_mm: height above the reference plane, mm.
        pose: pose index of each point.
        image_size: (width, height) of the camera, px.
        fringes: fringe count of the finest frequency across the projector.
        projector_width_px: projector extent along the fringe axis, px.
    """

    u: F64
    v: F64
    ray_xy: F64
    phi: F64
    z_mm: F64
    pose: npt.NDArray[np.int64]
    image_size: tuple[int, int]
    fringes: int
    projector_width_px: int

    def __post_init__(self) -> None:
        n = len(self.z_mm)
        for name in ("u", "v", "phi", "z_mm", "pose"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name}: {len(getattr(self, name))} values for {n} samples")
        if np.shape(self.ray_xy) != (n, 2):
            raise ValueError(f"ray_xy: expected shape ({n}, 2), got {np.shape(self.ray_xy)}")

    def subset(self, mask: npt.NDArray[np.bool_]) -> BoardSamples:
        """The samples where ``mask`` is True."""
        return BoardSamples(
            self.u[mask],
            self.v[mask],
            self.ray_xy[mask],
            self.phi[mask],
            self.z_mm[mask],
            self.pose[mask],
            self.image_size,
            self.fringes,
            self.projector_width_px,
        )

    def points_mm(self, plane: ReferencePlane) -> F64:
        """(n, 3) camera-frame points: the height ``z`` on each ray."""
        r = np.concatenate([self.ray_xy, np.ones((len(self.z_mm), 1))], axis=1)
        s = (self.z_mm - plane.offset_mm) / (r @ np.asarray(plane.normal, np.float64))
        return np.asarray(r * s[:, None], np.float64)


@dataclass
class SupportedRegion:
    """Where a model's fit data reach.

    Attributes:
        phase_rad: (lo, hi) finest phase range the data covered (with a margin), or None
            for any phase.
        height_grid_mm: (gh, gw, 2) per image cell (lo, hi) height bounds (with a margin;
            lo > hi marks a cell without data), or None for no per-cell bound.
        cell_px: (cell width, cell height) of the grid, px.
        field_px: (cx, cy, rx, ry) the image ellipse, px, inside which the camera model is
            supported (centre the distortion centre; semi-axes a normalised radius times the
            focal lengths), or None for the whole image. The camera's lens distortion is fitted
            from board points out to some radius only; beyond it (plus a margin the held-out
            error justifies) its polynomial extrapolates and no depth is given there.
        height_allowance_mm: a MEASURED height may pass the grid's bounds by this much (its noise:
            a surface on a bound keeps its pixels); the bounds themselves hold for the true height.
    """

    phase_rad: tuple[float, float] | None = None
    height_grid_mm: F64 | None = None
    cell_px: tuple[float, float] = (1.0, 1.0)
    field_px: tuple[float, float, float, float] | None = None
    height_allowance_mm: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "phase_rad": None if self.phase_rad is None else list(self.phase_rad),
            "height_grid_mm": None
            if self.height_grid_mm is None
            else np.round(self.height_grid_mm, 6).tolist(),
            "cell_px": list(self.cell_px),
            "field_px": None
            if self.field_px is None
            else [round(float(x), 4) for x in self.field_px],
            "height_allowance_mm": float(self.height_allowance_mm),
        }

    @classmethod
    def from_dict(cls, data: Any) -> SupportedRegion:
        if data is None:
            return cls()
        if not isinstance(data, dict):
            raise ValueError("supported_region: expected an object")
        phase = data.get("phase_rad")
        grid = data.get("height_grid_mm")
        try:
            g = None if grid is None else np.asarray(grid, np.float64)
            if g is not None and (g.ndim != 3 or g.shape[2] != 2):
                raise ValueError(f"height_grid_mm: expected (gh, gw, 2), got {g.shape}")
            cw, ch = (float(x) for x in data.get("cell_px", (1.0, 1.0)))
            ph = None if phase is None else (float(phase[0]), float(phase[1]))
            fp = data.get("field_px")
            fpx = None if fp is None else tuple(float(x) for x in fp)
            allowance = float(data.get("height_allowance_mm", 0.0))
        except (TypeError, IndexError, ValueError) as exc:
            raise ValueError(f"supported_region: malformed ({exc})") from None
        if cw <= 0 or ch <= 0:
            raise ValueError("supported_region: cell_px must be positive")
        if fpx is not None and (
            len(fpx) != 4 or not all(math.isfinite(x) for x in fpx) or fpx[2] <= 0 or fpx[3] <= 0
        ):
            raise ValueError(
                "supported_region: field_px must be 4 finite numbers (cx, cy, rx, ry), rx, ry > 0"
            )
        if not (math.isfinite(allowance) and allowance >= 0.0):
            raise ValueError("supported_region: height_allowance_mm must be finite and >= 0")
        return cls(ph, g, (cw, ch), fpx, allowance)

    def kernel_bounds(self, *, measured: bool = True) -> tuple[F32, float, float, float, float]:
        """(grid (gh, gw, 2) float32, 1/cell width, 1/cell height, phase lo, phase hi) for the
        kernel
        (``measured``: the grid widened by :attr:`height_allowance_mm`, as the kernel tests measured
        heights); an unbounded region is a 1×1 grid of (−inf, inf)."""
        if self.height_grid_mm is None:
            grid = np.array([[[-np.inf, np.inf]]], np.float32)
            inv_w = inv_h = 0.0
        else:
            g = np.array(self.height_grid_mm, np.float64)
            if measured and self.height_allowance_mm > 0.0:
                covered = g[..., 1] >= g[..., 0]
                g[..., 0] = np.where(covered, g[..., 0] - self.height_allowance_mm, g[..., 0])
                g[..., 1] = np.where(covered, g[..., 1] + self.height_allowance_mm, g[..., 1])
            grid = np.ascontiguousarray(g, np.float32)
            inv_w, inv_h = 1.0 / self.cell_px[0], 1.0 / self.cell_px[1]
        lo, hi = self.phase_rad if self.phase_rad is not None else (-math.inf, math.inf)
        return grid, inv_w, inv_h, lo, hi

    def outside(self, height_mm: npt.ArrayLike, phase: npt.ArrayLike, *, measured: bool = False
                ) -> npt.NDArray[np.bool_]:
        """(H, W) True where (pixel, height, phase) is outside the region (NaN counts as outside);
        ``measured``: the heights are measured ones, allowed :attr:`height_allowance_mm` past
        the bounds."""
        h = np.asarray(height_mm, np.float64)
        p = np.asarray(phase, np.float64)
        grid, inv_w, inv_h, lo, hi = self.kernel_bounds(measured=measured)
        rows, cols = h.shape
        ci = np.minimum((np.arange(rows) * inv_h).astype(np.int64), grid.shape[0] - 1)
        cj = np.minimum((np.arange(cols) * inv_w).astype(np.int64), grid.shape[1] - 1)
        g = grid.astype(np.float64)[ci][:, cj]
        inside = (h >= g[..., 0]) & (h <= g[..., 1]) & (p >= lo) & (p <= hi)
        u_lo, u_hi = self.column_bounds(rows, cols)
        u = np.arange(cols, dtype=np.float32)
        inside &= (u[None, :] >= u_lo[:, None]) & (u[None, :] <= u_hi[:, None])
        return np.asarray(~inside, np.bool_)

    def column_bounds(self, rows: int, cols: int) -> tuple[F32, F32]:
        """(rows,) float32 lowest and highest supported column of every image row (the
        chord of :attr:`field_px`; lo > hi for a row that misses it; ±inf without a field limit).
        The kernel and :meth:`outside` both test ``lo <= u <= hi``."""
        if self.field_px is None:
            return np.full(rows, -np.inf, np.float32), np.full(rows, np.inf, np.float32)
        cx, cy, rx, ry = self.field_px
        t = 1.0 - ((np.arange(rows, dtype=np.float64) - cy) / ry) ** 2
        half = rx * np.sqrt(np.maximum(t, 0.0))
        lo = np.where(t >= 0, cx - half, np.inf)
        hi = np.where(t >= 0, cx + half, -np.inf)
        return lo.astype(np.float32), hi.astype(np.float32)

    def field_limited(self, field_px: tuple[float, float, float, float] | None) -> SupportedRegion:
        """This region with the camera-field ellipse ``field_px`` (see the attributes)."""
        return SupportedRegion(
            self.phase_rad, self.height_grid_mm, self.cell_px, field_px, self.height_allowance_mm
        )


def region_from_samples(
    samples: BoardSamples,
    *,
    cells: tuple[int, int] = (16, 12),
    margin_mm: float = 2.0,
    dilate: int = 1,
) -> SupportedRegion:
    """The (u, v, height) region the board samples cover: per grid cell the samples' height
    range ± ``margin_mm``; cells within ``dilate`` cells of covered ones take their
    neighbours' union; cells farther away support nothing. Phase: the samples' range."""
    w, h = samples.image_size
    gw, gh = cells
    cw, ch = w / gw, h / gh
    ok = np.isfinite(samples.z_mm) & np.isfinite(samples.phi)
    ci = np.clip((samples.v[ok] / ch).astype(np.int64), 0, gh - 1)
    cj = np.clip((samples.u[ok] / cw).astype(np.int64), 0, gw - 1)
    lo = np.full((gh, gw), np.inf)
    hi = np.full((gh, gw), -np.inf)
    np.minimum.at(lo, (ci, cj), samples.z_mm[ok])
    np.maximum.at(hi, (ci, cj), samples.z_mm[ok])
    lo2, hi2 = lo.copy(), hi.copy()
    for di in range(-dilate, dilate + 1):
        for dj in range(-dilate, dilate + 1):
            sl = np.roll(np.roll(lo, di, 0), dj, 1)
            sh = np.roll(np.roll(hi, di, 0), dj, 1)
            if di > 0:
                sl[:di], sh[:di] = np.inf, -np.inf
            if di < 0:
                sl[di:], sh[di:] = np.inf, -np.inf
            if dj > 0:
                sl[:, :dj], sh[:, :dj] = np.inf, -np.inf
            if dj < 0:
                sl[:, dj:], sh[:, dj:] = np.inf, -np.inf
            lo2 = np.minimum(lo2, sl)
            hi2 = np.maximum(hi2, sh)
    covered = hi2 >= lo2
    grid = np.stack(
        [np.where(covered, lo2 - margin_mm, 1.0), np.where(covered, hi2 + margin_mm, -1.0)], axis=-1
    )
    p = samples.phi[ok]
    return SupportedRegion((float(p.min()), float(p.max())) if p.size else None, grid, (cw, ch))


def missing_cells(region: SupportedRegion) -> list[str]:
    """Names of the image ninths (``"top left"`` … ``"bottom right"``) with no supported cell."""
    if region.height_grid_mm is None:
        return []
    g = region.height_grid_mm
    covered = g[..., 1] >= g[..., 0]
    gh, gw = covered.shape
    names = []
    for i, rn in enumerate(("top", "middle", "bottom")):
        for j, cn in enumerate(("left", "centre", "right")):
            block = covered[i * gh // 3:(i + 1) * gh // 3, j * gw // 3:(j + 1) * gw // 3]
            if block.size and not block.any():
                names.append("centre" if (rn, cn) == ("middle", "centre") else f"{rn} {cn}")
    return names


class DepthModel(ABC):
    """One phase-to-height model: fitted from board samples, evaluated through
    :class:`HeightTables`.

    Implementations: :class:`app.core.eq5.Eq5Model` (``"eq5"``, Le et al. 2018 Eq. (5)) and
    :class:`app.core.geometric.GeometricModel` (``"geometric"``).
    """

    name: ClassVar[str]
    region: SupportedRegion
    #: the fits with one board pose left out each (empty: unknown): their spread is the
    #: model's own uncertainty (:meth:`height_deviations`)
    jackknife: Sequence[DepthModel]
    #: another model form fitted to the same data (None: none): where the two disagree the
    #: choice between them is uncertain too
    alternative: DepthModel | None
    #: the scale of the :attr:`alternative`'s row: 1 where the data could not reject it; where
    #: they did at p-value p, √(p·(1 − p)) (the spread of a choice made with probability p
    #: of being wrong), 0 where p is nil
    alternative_weight: float = 1.0

    @classmethod
    @abstractmethod
    def fit(cls, samples: BoardSamples, plane: ReferencePlane) -> DepthModel:
        """Fit to board samples; ``ValueError`` if they do not determine the model."""

    @abstractmethod
    def height_tables(self, image_size: tuple[int, int], plane: ReferencePlane) -> HeightTables:
        """Kernel tables for a ``(width, height)`` image and the record's reference plane."""

    @abstractmethod
    def height_at(self, u: F64, v: F64, ray_xy: F64, phi: F64, plane: ReferencePlane) -> F64:
        """Reference float64 heights (mm) at pixels (u, v) with rays ``ray_xy`` (n, 2) and
        phases φ."""

    @abstractmethod
    def phase_at(self, u: F64, v: F64, ray_xy: F64, height_mm: F64, plane: ReferencePlane) -> F64:
        """(n,) the finest phase (rad) this model assigns to a surface at ``height_mm`` (n,) at
        pixels (u, v) with rays ``ray_xy`` (n, 2): the inverse of :meth:`height_at`."""

    def height_deviations(self, u: F64, v: F64, ray_xy: F64, height_mm: F64,
                          plane: ReferencePlane) -> F64:
        """(K, n) float64 height errors (mm) of this model whose Gram matrix is the covariance of
        its heights at n (pixel, height) places: ``cov(h_i, h_j) = Σ_k D[k, i]·D[k, j]``.

        The rows are the delete-one-pose jackknife (G rows, ``√((G−1)/G)·(h_g − h̄)``: each
        leave-one-pose-out fit maps the phase this model gives at the place to a height) and,
        with an :attr:`alternative`, its height minus this model's. The same board poses move
        every place's height, so the errors of two places are correlated as the rows say.
        K = 0 without a jackknife of at least 3 poses (the uncertainty is unknown).
        """
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        n = len(rxy)
        g = len(self.jackknife)
        if g < 3:
            return np.zeros((0, n))
        h = np.broadcast_to(np.asarray(height_mm, np.float64).ravel(), (n,))
        uu = np.broadcast_to(np.asarray(u, np.float64).ravel(), (n,))
        vv = np.broadcast_to(np.asarray(v, np.float64).ravel(), (n,))
        phi = self.phase_at(uu, vv, rxy, h, plane)
        hs = np.stack([m.height_at(uu, vv, rxy, phi, plane) for m in self.jackknife])
        rows = math.sqrt((g - 1) / g) * (hs - hs.mean(axis=0))
        if self.alternative is not None:
            alt = self.alternative.height_at(uu, vv, rxy, phi, plane) - h
            rows = np.concatenate([rows, self.alternative_weight * alt[None]])
        return np.asarray(rows, np.float64)

    def total_height_deviations(self, u: F64, v: F64, ray_xy: F64, height_mm: F64,
                                plane: ReferencePlane) -> F64:
        """(K, n) as :meth:`height_deviations`, but of the whole calibration where the model
        carries it (the camera, its lens model and the reference plane refitted with each pose
        left out, not only this model): the error of a height above the reference plane. A model
        without such a jackknife gives :meth:`height_deviations`."""
        return self.height_deviations(u, v, ray_xy, height_mm, plane)

    def total_point_deviations(self, u: F64, v: F64, ray_xy: F64, height_mm: F64,
                               plane: ReferencePlane) -> F64:
        """(K, n, 3) errors (mm) of the camera-frame points at n (pixel, height) places whose
        Gram matrix is their covariance: here the rows of :meth:`total_height_deviations`, each
        moving its point along its ray (``r / (n·r)`` per mm of height); a model that carries
        its camera's refits moves the points sideways as well."""
        d = self.total_height_deviations(u, v, ray_xy, height_mm, plane)
        rxy = np.asarray(ray_xy, np.float64).reshape(-1, 2)
        r = np.concatenate([rxy, np.ones((len(rxy), 1))], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            along = r / (r @ np.asarray(plane.normal, np.float64))[:, None]
        return np.asarray(d[:, :, None] * along[None], np.float64)

    def height_sigma(self, u: F64, v: F64, ray_xy: F64, height_mm: F64,
                     plane: ReferencePlane) -> F64:
        """(n,) 1-σ uncertainty (mm) of this model's height at pixels (u, v) (rays ``ray_xy``
        (n, 2)) for a surface at ``height_mm``: the root sum of squares of
        :meth:`total_height_deviations`; NaN without a jackknife."""
        d = self.total_height_deviations(u, v, ray_xy, height_mm, plane)
        if d.shape[0] == 0:
            return np.full(d.shape[1], np.nan)
        return np.asarray(np.sqrt(np.sum(d * d, axis=0)), np.float64)

    @abstractmethod
    def params(self) -> dict[str, Any]:
        """The model's parameters as a JSON object (without name and region)."""

    @classmethod
    @abstractmethod
    def from_params(cls, params: dict[str, Any], region: SupportedRegion) -> DepthModel:
        """Inverse of :meth:`params`; ``ValueError`` naming what is wrong."""

    def to_dict(self) -> dict[str, Any]:
        out = {"name": self.name, **self.params(), "supported_region": self.region.to_dict()}
        if self.jackknife:  # the model's own uncertainty, re-derived at load
            out["jackknife"] = [m.params() for m in self.jackknife]
        if self.alternative is not None:
            out["alternative"] = self.alternative.params()
            if self.alternative_weight != 1.0:
                out["alternative_weight"] = self.alternative_weight
        return out


def row_tables_zero(image_size: tuple[int, int]) -> tuple[F64, F64]:
    """(u_norm zeros (W,), row_coefs zeros (H, 12)) for a model without row terms."""
    w, h = (int(x) for x in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size: invalid {image_size}")
    return np.zeros(w), np.zeros((h, 12))


__all__ = [
    "COLUMN_ITERATIONS",
    "BoardSamples",
    "DepthModel",
    "HeightTables",
    "ReferencePlane",
    "SupportedRegion",
    "column_term",
    "epipolar_lines",
    "missing_cells",
    "region_from_samples",
]
