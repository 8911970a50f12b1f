"""Phase-to-height models precomputed per pixel (Eq. (5) and the geometric model alike).

Every :class:`~app.core.depth_model.DepthModel` gives :class:`~app.core.depth_model.HeightTables`;
:func:`pixel_tables` turns them into per-pixel a0, a1, b0, b1 (with the ray quotients)
for the numpy oracle. For Eq. (5):

For a fixed pixel (u', v') the numerator and denominator of Eq. (5) are linear in φ':

    height = (a0 + a1·φ') / (b0 + b1·φ'),   φ' = (φ − φ0) / sφ

with
    a0 = 1  + c2 u' + c4 v' + c6 u'² + c8 v'² + c10 u'v'     a1 = c1 + c3 u' + ... + c11 u'v'
    b0 = d0 + d2 u' + d4 v' + d6 u'² + d8 v'² + d10 u'v'     b1 = d1 + d3 u' + ... + d11 u'v'

so :func:`model_tables` evaluates the four quadratic polynomials once per image size
and a depth costs two multiply-adds and one division per pixel.

A denominator is *singular* when |b0 + b1φ'| ≤ ``SINGULAR_RTOL``·(|b0| + |b1φ'|): it is
then below a few tens of float32 rounding steps of its own terms, so its sign and
size — hence the height — are noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration
from app.core.depth_model import HeightTables, column_term, epipolar_lines
from app.core.eq5 import Eq5Model

SINGULAR_RTOL = 1e-5


@dataclass(frozen=True)
class ModelTables:
    """Per-pixel Eq. (5) coefficients for one image size.

    Attributes:
        a0, a1, b0, b1: (H, W) arrays (float32 or float64).
        phi0, inv_sphi: phase normalisation, ``φ' = (φ − phi0)·inv_sphi``.
        cubic: ``t = φ' + cubic·φ'³`` enters the rational form (0 for Eq. (5)).
        radial_k, alpha, beta: a radial projector lens, ``radial_k`` on the (H, W) epipolar
            lines ``y = α + β·t`` (:func:`~app.core.depth_model.column_term`; None where
            ``radial_k`` is 0).
    """

    a0: npt.NDArray[Any]
    a1: npt.NDArray[Any]
    b0: npt.NDArray[Any]
    b1: npt.NDArray[Any]
    phi0: float
    inv_sphi: float
    cubic: float = 0.0
    radial_k: float = 0.0
    alpha: npt.NDArray[np.float64] | None = None
    beta: npt.NDArray[np.float64] | None = None


def model_tables(
    numerator: npt.ArrayLike,
    denominator: npt.ArrayLike,
    normalization: dict[str, tuple[float, float]],
    image_size: tuple[int, int],
    *,
    dtype: Any = np.float64,
) -> ModelTables:
    """Evaluate the u/v parts of Eq. (5) for every pixel of a ``(width, height)`` image.

    Args:
        numerator: c1..c11 (11 values); the constant term is fixed at 1.
        denominator: d0..d11 (12 values).
        normalization: ``{"u": (u0, su), "v": (v0, sv), "phi": (φ0, sφ)}``.
        image_size: (width, height) pixels; u is the column, v the row index.
        dtype: float dtype of the tables.

    Returns:
        :class:`ModelTables` with (height, width) arrays.
    """
    polys, (u0, su), (v0, sv), (p0, sp), (w, h) = _checked_model(numerator, denominator,
                                                                 normalization, image_size)
    up, vp = np.meshgrid((np.arange(w) - u0) / su, (np.arange(h) - v0) / sv)
    # basis terms shared by all four polynomials: 1, u', v', u'², v'², u'v'
    basis = (np.ones((h, w)), up, vp, up**2, vp**2, up * vp)

    def poly(coefs: tuple[float, ...]) -> npt.NDArray[Any]:
        return np.asarray(sum(k * b for k, b in zip(coefs, basis, strict=True)), dtype=dtype)

    a0, a1, b0, b1 = (poly(p) for p in polys)
    return ModelTables(a0, a1, b0, b1, float(p0), 1.0 / float(sp))


def calibration_model_tables(calibration: Calibration, *, dtype: Any = np.float64) -> ModelTables:
    """Per-pixel tables of the calibration's depth model (any model)."""
    from app.recon.points import calibration_ray_tables, ray_quotients

    tables = calibration_height_tables(calibration)
    q = ray_quotients(calibration_ray_tables(calibration), dtype=np.float64)
    return pixel_tables(tables, q, dtype=dtype)


def calibration_height_tables(calibration: Calibration) -> HeightTables:
    """The kernel's :class:`~app.core.depth_model.HeightTables` of the calibration's model."""
    return calibration.model.height_tables(calibration.image_size, calibration.reference_plane)


def pixel_tables(tables: HeightTables, ray_q: npt.ArrayLike, *,
                 dtype: Any = np.float64) -> ModelTables:
    """Per-pixel a0, a1, b0, b1 from row and ray coefficients.

    Args:
        tables: the model's height tables (float32 numbers are widened to float64).
        ray_q: (H, W, 3) ray quotients ``r/(n·r)``.
    """
    q = np.asarray(ray_q, np.float64)
    x = np.asarray(tables.u_norm, np.float64)[None, :]
    k = np.asarray(tables.row_coefs, np.float64)
    g = np.asarray(tables.ray_coefs, np.float64).reshape(4, 3)
    if q.shape != (k.shape[0], x.shape[1], 3):
        raise ValueError(f"ray_q: shape {q.shape} does not match the tables' "
                         f"{(k.shape[0], x.shape[1], 3)}")
    out = []
    for i in range(4):
        row = (k[:, 3 * i + 2, None] * x + k[:, 3 * i + 1, None]) * x + k[:, 3 * i, None]
        if np.any(g[i]):
            row = row + np.nan_to_num(q @ g[i], nan=np.nan)
        out.append(np.asarray(row, dtype=dtype))
    radial_k = float(tables.radial_k)
    alpha, beta = epipolar_lines(tables.cross_coefs, q) if radial_k else (None, None)
    return ModelTables(out[0], out[1], out[2], out[3], float(tables.phi0), float(tables.inv_sphi),
                       float(tables.cubic), radial_k, alpha, beta)


def _checked_model(
    numerator: npt.ArrayLike, denominator: npt.ArrayLike,
    normalization: dict[str, tuple[float, float]], image_size: tuple[int, int],
) -> tuple[list[tuple[float, ...]], tuple[float, float], tuple[float, float], tuple[float, float],
           tuple[int, int]]:
    """Validated Eq. (5) parts: the coefficients of a0, a1, b0, b1 on the basis
    (1, u', v', u'², v'², u'v'), the u, v and φ normalisations and (width, height)."""
    c = np.asarray(numerator, dtype=np.float64).ravel()
    d = np.asarray(denominator, dtype=np.float64).ravel()
    if c.shape != (11,) or not np.all(np.isfinite(c)):
        raise ValueError(f"numerator: need 11 finite values, got shape {c.shape}")
    if d.shape != (12,) or not np.all(np.isfinite(d)):
        raise ValueError(f"denominator: need 12 finite values, got shape {d.shape}")
    w, h = (int(x) for x in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size: invalid {image_size}")
    (u0, su), (v0, sv), (p0, sp) = (normalization[k] for k in ("u", "v", "phi"))
    if su == 0 or sv == 0 or sp == 0 or not all(math.isfinite(x) for x in (u0, su, v0, sv, p0, sp)):
        raise ValueError("normalization: needs finite offsets and non-zero scales")
    polys = [
        (1.0, *(float(x) for x in c[1:10:2])),
        tuple(float(x) for x in c[0:11:2]),
        tuple(float(x) for x in d[0:12:2]),
        tuple(float(x) for x in d[1:12:2]),
    ]
    return polys, (u0, su), (v0, sv), (p0, sp), (w, h)


@dataclass(frozen=True)
class RowCoefficients:
    """Eq. (5) for one image size as per-row quadratics in the normalised column u'.

    For row v each of a0, a1, b0, b1 is ``α + β·u' + γ·u'²``; evaluating that costs
    two multiply-adds, where a table would cost a memory read per pixel.

    Attributes:
        u_norm: (W,) float32 u' of every column.
        coefs: (H, 12) float32 (α, β, γ) of a0, a1, b0, b1 per row.
        phi0, inv_sphi: phase normalisation, ``φ' = (φ − phi0)·inv_sphi``.
    """

    u_norm: npt.NDArray[np.float32]
    coefs: npt.NDArray[np.float32]
    phi0: float
    inv_sphi: float


def row_coefficients(
    numerator: npt.ArrayLike,
    denominator: npt.ArrayLike,
    normalization: dict[str, tuple[float, float]],
    image_size: tuple[int, int],
) -> RowCoefficients:
    """The Eq. (5) u/v parts of a ``(width, height)`` image as per-row quadratics in u'
    (same arguments as :func:`model_tables`)."""
    _checked_model(numerator, denominator, normalization, image_size)
    t = Eq5Model(np.asarray(numerator), np.asarray(denominator), dict(normalization)).height_tables(
        image_size, None)  # type: ignore[arg-type]  # Eq. (5) does not use the plane
    return RowCoefficients(u_norm=t.u_norm.astype(np.float32),
                           coefs=np.ascontiguousarray(t.row_coefs, dtype=np.float32),
                           phi0=t.phi0, inv_sphi=t.inv_sphi)


def evaluate_height(
    tables: ModelTables, phase: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """Height above the reference plane from the unwrapped finest phase.

    Args:
        tables: per-pixel model tables of the image size.
        phase: (H, W) unwrapped finest-frequency phase, radians (NaN allowed).

    Returns:
        ``(height_mm, singular)``: (H, W) float64 height (inf/NaN where singular) and
        the (H, W) bool singular-denominator mask.
    """
    phi = np.asarray(phase, dtype=np.float64)
    if phi.shape != tables.a0.shape:
        raise ValueError(f"phase: shape {phi.shape} does not match the tables' {tables.a0.shape}")
    height, singular, _ = evaluate_height_slope(tables, phi)
    return height, singular


def evaluate_height_slope(
    tables: ModelTables, phase: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.float64]]:
    """:func:`evaluate_height` and ∂height/∂φ (mm/rad) of the closed form."""
    phi = np.asarray(phase, dtype=np.float64)
    if phi.shape != tables.a0.shape:
        raise ValueError(f"phase: shape {phi.shape} does not match the tables' {tables.a0.shape}")
    pp = (phi - tables.phi0) * tables.inv_sphi
    alpha = 0.0 if tables.alpha is None else tables.alpha
    beta = 0.0 if tables.beta is None else tables.beta
    t, dt = column_term(pp, tables.cubic, alpha, beta, tables.radial_k)
    b1p = tables.b1 * t
    den = tables.b0 + b1p
    num = tables.a0 + tables.a1 * t
    singular = np.abs(den) <= SINGULAR_RTOL * (np.abs(tables.b0) + np.abs(b1p))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        height = num / den
        slope = (tables.a1 * tables.b0 - tables.a0 * tables.b1) / (den * den) * tables.inv_sphi * dt
    return height, singular, slope


def outside_volume(
    height_mm: npt.ArrayLike, height_range_mm: tuple[float, float], margin_mm: float
) -> npt.NDArray[np.bool_]:
    """Heights outside ``[min − margin, max + margin]`` (NaN counts as outside)."""
    h = np.asarray(height_mm)
    lo, hi = height_range_mm
    return ~((h >= lo - margin_mm) & (h <= hi + margin_mm))
