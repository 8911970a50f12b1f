"""Eq. (5) of Le et al. (2018): evaluation and the 23-coefficient fit (linear start + LM).

All functions work in the normalised coordinates u', v', φ' of
:mod:`app.calib.calibration`; :func:`normalize` maps pixels and radians into them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from app.calib.calibration import N_DENOMINATOR, N_NUMERATOR, Calibration

F64 = npt.NDArray[np.float64]


def basis(u: npt.ArrayLike, v: npt.ArrayLike, phi: npt.ArrayLike) -> F64:
    """The 12 monomials [1, φ, u, φu, v, φv, u², φu², v², φv², uv, φuv], shape (n, 12).

    The denominator is ``basis @ d``; the numerator is ``1 + basis[:, 1:] @ c``.
    """
    u = np.asarray(u, np.float64).ravel()
    v = np.asarray(v, np.float64).ravel()
    p = np.asarray(phi, np.float64).ravel()
    if not (u.shape == v.shape == p.shape):
        raise ValueError(f"u, v, phi: shapes differ {u.shape} {v.shape} {p.shape}")
    cols = []
    for m in (np.ones_like(u), u, v, u * u, v * v, u * v):
        cols += [m, p * m]
    return np.stack(cols, axis=1)


def evaluate(numerator: npt.ArrayLike, denominator: npt.ArrayLike, u: npt.ArrayLike,
             v: npt.ArrayLike, phi: npt.ArrayLike) -> F64:
    """Height z (mm) of Eq. (5) at normalised (u', v', φ'); flat float64 array."""
    b = basis(u, v, phi)
    num = 1.0 + b[:, 1:] @ np.asarray(numerator, np.float64)
    den = b @ np.asarray(denominator, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / den


def normalize(calibration_norm: dict[str, tuple[float, float]], u: npt.ArrayLike, v: npt.ArrayLike,
              phi: npt.ArrayLike) -> tuple[F64, F64, F64]:
    """Pixels (u = column, v = row) and phase (rad) → u', v', φ' for ``normalization``."""
    out = []
    for key, x in (("u", u), ("v", v), ("phi", phi)):
        off, scale = calibration_norm[key]
        out.append((np.asarray(x, np.float64) - off) / scale)
    return out[0], out[1], out[2]


def height_mm(calibration: Calibration, u: npt.ArrayLike, v: npt.ArrayLike, phi: npt.ArrayLike) -> F64:
    """Height above the reference plane (mm) at pixel (u, v) with finest-frequency phase φ (rad).

    A plain reference implementation of the calibration's model (flat float64 array).
    """
    un, vn, pn = normalize(calibration.normalization, u, v, phi)
    return evaluate(calibration.numerator, calibration.denominator, un, vn, pn)


@dataclass
class Eq5Fit:
    """Fitted coefficients and the residuals z_model − z (mm) of every point."""

    numerator: F64
    denominator: F64
    residuals_mm: F64
    linear_rms_mm: float


def fit_eq5(u: npt.ArrayLike, v: npt.ArrayLike, phi: npt.ArrayLike, z_mm: npt.ArrayLike) -> Eq5Fit:
    """Fit the 23 coefficients to control points (already normalised u', v', φ').

    A linear least-squares start from ``z·den − num = 0`` (numerator constant 1), then
    Levenberg–Marquardt on Σ (z_model − z)².

    Args:
        u, v, phi: (n,) normalised coordinates.
        z_mm: (n,) heights above the reference plane, mm.

    Raises:
        ValueError: fewer than 23 points, or a rank-deficient system (degenerate poses).
    """
    b = basis(u, v, phi)
    z = np.asarray(z_mm, np.float64).ravel()
    if z.shape[0] != b.shape[0]:
        raise ValueError(f"z_mm: {z.shape[0]} heights for {b.shape[0]} points")
    n_params = N_NUMERATOR + N_DENOMINATOR
    if z.shape[0] < 2 * n_params:
        raise ValueError(f"points: need at least {2 * n_params} control points for 23 coefficients, got {z.shape[0]}")
    a = np.concatenate([z[:, None] * b, -b[:, 1:]], axis=1)
    col_scale = np.linalg.norm(a, axis=0)
    col_scale[col_scale == 0] = 1.0
    sol, _, rank, sv = np.linalg.lstsq(a / col_scale, np.ones_like(z), rcond=None)
    if rank < n_params or sv[-1] < 1e-10 * sv[0]:
        raise ValueError(
            "poses: degenerate — the control points do not determine the 23 coefficients "
            f"(rank {rank} of {n_params}); use more poses, tilted and spread through the volume"
        )
    p0 = sol / col_scale
    den0, num0 = p0[:N_DENOMINATOR], p0[N_DENOMINATOR:]
    lin_res = (1.0 + b[:, 1:] @ num0) / (b @ den0) - z

    def residuals(p: F64) -> F64:
        return (1.0 + b[:, 1:] @ p[N_DENOMINATOR:]) / (b @ p[:N_DENOMINATOR]) - z

    def jacobian(p: F64) -> F64:
        num = 1.0 + b[:, 1:] @ p[N_DENOMINATOR:]
        den = b @ p[:N_DENOMINATOR]
        return np.concatenate([-(num / den**2)[:, None] * b, b[:, 1:] / den[:, None]], axis=1)

    res = least_squares(residuals, p0, jac=jacobian, method="lm", x_scale="jac", max_nfev=2000)
    p = res.x if np.all(np.isfinite(res.x)) else p0
    r = residuals(p)
    if not np.all(np.isfinite(r)) or np.sqrt(np.mean(r**2)) > np.sqrt(np.mean(lin_res**2)):
        p, r = p0, lin_res
    return Eq5Fit(
        numerator=p[N_DENOMINATOR:].copy(),
        denominator=p[:N_DENOMINATOR].copy(),
        residuals_mm=r,
        linear_rms_mm=float(np.sqrt(np.mean(lin_res**2))),
    )


def choose_normalization(u: npt.ArrayLike, v: npt.ArrayLike, phi: npt.ArrayLike, z_mm: npt.ArrayLike,
                         image_size: tuple[int, int]) -> dict[str, tuple[float, float]]:
    """Normalisation for the fit: pixels to about [-1, 1]; φ scaled by its half range.

    φ0 is placed where the image-centre height is the calibration's extreme height, not
    0: with the numerator constant fixed at 1, a centre of zero height would make the
    numerator vanish there and the parametrisation singular.
    """
    w, h = image_size
    uu = np.asarray(u, np.float64).ravel()
    vv = np.asarray(v, np.float64).ravel()
    pp = np.asarray(phi, np.float64).ravel()
    z = np.asarray(z_mm, np.float64).ravel()
    norm_u = ((w - 1) / 2.0, w / 2.0)
    norm_v = ((h - 1) / 2.0, h / 2.0)
    p_mid = float(np.mean(pp))
    p_half = float(np.ptp(pp)) / 2.0 or 1.0
    # Height is close to linear in (u, v, φ) over the volume: z ≈ a + b u' + c v' + e φ'.
    un = (uu - norm_u[0]) / norm_u[1]
    vn = (vv - norm_v[0]) / norm_v[1]
    pn = (pp - p_mid) / p_half
    design = np.stack([np.ones_like(un), un, vn, pn], axis=1)
    coef, *_ = np.linalg.lstsq(design, z, rcond=None)
    z_far = float(z[np.argmax(np.abs(z))])
    if abs(coef[3]) > 1e-12:
        p_mid += p_half * (z_far - coef[0]) / coef[3]
    return {"u": norm_u, "v": norm_v, "phi": (p_mid, p_half)}
