"""Levenberg–Marquardt for tall dense least-squares problems, its steps from JᵀJ.

The joint calibration fit (:func:`app.calib.refine.refine_board_poses`) has ~60,000 residuals
and ~55 parameters. MINPACK's ``lmder`` (scipy's ``method="lm"``) factors each Jacobian with
its own unblocked Householder QR, which streams the whole 28 MB Jacobian once per column:
~0.15 s per evaluation, more than the residuals and the Jacobian together (LAPACK's blocked QR
is little faster at 55 columns). Here one BLAS product JᵀJ (n × n, ~15 ms) carries every step;
the damped systems are solved by Cholesky in the columns' scale, where the fit's normal
matrix is well enough conditioned that the solutions agree with MINPACK's to ~1e-11
(``tests/calib/test_levenberg.py``). The method is MINPACK's (Moré 1978): steps of
``min ‖J δ + r‖² + λ ‖D δ‖²`` with D the columns' largest norms so far (``x_scale="jac"``),
Gauss–Newton (λ = 0) while those succeed, as MINPACK's wide first trust region is; the damping
then follows Nielsen's rule (Madsen, Nielsen & Tingleff, *Methods for non-linear least
squares problems*, 2004, §3.2) instead of MINPACK's trust-region radius.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg

F64 = npt.NDArray[np.float64]

#: the initial damping relative to the scaled JᵀJ's diagonal (Madsen et al.'s τ)
INITIAL_DAMPING = 1e-3
#: the damping, relative to the scaled JᵀJ's unit diagonal, below which steps are Gauss–Newton
MIN_DAMPING = 1e-12


@dataclass(frozen=True)
class LeastSquaresFit:
    """The solution of :func:`levenberg_marquardt`.

    Attributes:
        x: (n,) the parameters at the least cost found.
        cost: ½ ‖r(x)‖².
        nfev, njev: evaluations of the residuals and of the Jacobian.
        converged: True when a tolerance was met, False when ``max_nfev`` ran out.
    """

    x: F64
    cost: float
    nfev: int
    njev: int
    converged: bool


def _damped_step(normal: F64, grad: F64, scale: F64, damping: float) -> F64:
    """δ solving (JᵀJ + λ D²) δ = −Jᵀr, in the columns' scale (unit diagonal) for Cholesky."""
    scaled = normal / np.outer(scale, scale)
    scaled[np.diag_indices_from(scaled)] += damping
    rhs = -grad / scale
    try:
        step = scipy.linalg.cho_solve(scipy.linalg.cho_factor(scaled, check_finite=False), rhs,
                                      check_finite=False)
    except np.linalg.LinAlgError:  # singular at λ = 0: the least-norm step
        step, *_ = np.linalg.lstsq(scaled, rhs, rcond=None)
    return np.asarray(step / scale, np.float64)


def levenberg_marquardt(
    fun: Callable[[F64], F64],
    jac: Callable[[F64], F64],
    x0: F64,
    *,
    max_nfev: int = 100,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
    gtol: float = 1e-8,
) -> LeastSquaresFit:
    """Minimise ½ ‖fun(x)‖² from ``x0`` by Levenberg–Marquardt.

    Args:
        fun: x (n,) → residuals (m,), m ≥ n.
        jac: x (n,) → its Jacobian (m, n).
        x0: (n,) the start.
        max_nfev: the most evaluations of ``fun``.
        ftol: stop when an accepted step lowers the cost by less than ``ftol`` × cost and the
            model predicted no more.
        xtol: stop when the scaled step ‖D δ‖ is below ``xtol`` × (``xtol`` + ‖D x‖).
        gtol: stop when the largest cosine between ``r`` and a column of J is below ``gtol``.
        (scipy's ``least_squares`` tolerances, with its defaults.)

    Returns:
        :class:`LeastSquaresFit`.

    Raises:
        ValueError: ``x0`` not a finite 1-D array, fewer residuals than parameters, a Jacobian
            of the wrong shape, or non-finite residuals at ``x0``.
    """
    x = np.array(x0, np.float64)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError(f"x0: need a finite 1-D array, got shape {x.shape}")
    if max_nfev < 1:
        raise ValueError(f"max_nfev: need ≥ 1, got {max_nfev}")
    n = x.size
    r = np.asarray(fun(x), np.float64)
    if r.ndim != 1 or r.size < n:
        raise ValueError(f"fun: need ≥ {n} residuals (one per parameter), got {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("fun: residuals at x0 are not finite")
    cost = 0.5 * float(r @ r)
    nfev, njev = 1, 0
    scale = np.zeros(n)
    damping = 0.0  # Gauss–Newton steps until one fails, as MINPACK's wide first region
    nu = 2.0
    while True:
        j = np.asarray(jac(x), np.float64)
        njev += 1
        if j.shape != (r.size, n):
            raise ValueError(f"jac: expected shape {(r.size, n)}, got {j.shape}")
        normal = j.T @ j  # (n, n): BLAS's matrix product, one pass over J
        grad = j.T @ r
        norms = np.sqrt(np.diag(normal))  # J's column norms
        scale = np.maximum(scale, np.where(norms > 0, norms, 1.0))
        r_norm = float(np.sqrt(2.0 * cost))
        if r_norm == 0.0 or np.max(np.abs(grad) / (norms * r_norm + (norms == 0))) <= gtol:
            return LeastSquaresFit(x, cost, nfev, njev, True)
        while True:
            step = _damped_step(normal, grad, scale, damping)
            x_new = x + step
            r_new = np.asarray(fun(x_new), np.float64)
            nfev += 1
            cost_new = 0.5 * float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            predicted = -float(grad @ step + 0.5 * step @ normal @ step)
            gain = (cost - cost_new) / predicted if predicted > 0 else -1.0
            small_step = (float(np.linalg.norm(scale * step))
                          <= xtol * (xtol + float(np.linalg.norm(scale * x))))
            if gain > 0:
                reduction = cost - cost_new
                x, r, cost = x_new, r_new, cost_new
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                if damping < MIN_DAMPING:
                    damping = 0.0
                nu = 2.0
                if small_step or (reduction <= ftol * cost_new and predicted <= ftol * cost_new):
                    return LeastSquaresFit(x, cost, nfev, njev, True)
                if nfev >= max_nfev:
                    return LeastSquaresFit(x, cost, nfev, njev, False)
                break
            if damping == 0.0:
                damping = INITIAL_DAMPING * float(np.max((norms / scale) ** 2))
            else:
                damping *= nu
                nu *= 2.0
            if small_step:
                return LeastSquaresFit(x, cost, nfev, njev, True)
            if nfev >= max_nfev:
                return LeastSquaresFit(x, cost, nfev, njev, False)
