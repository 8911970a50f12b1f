"""Levenberg–Marquardt on JᵀJ against analytic minima and MINPACK (scipy's ``method="lm"``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import pytest
from scipy.optimize import least_squares

from app.calib.levenberg import levenberg_marquardt

F64 = npt.NDArray[np.float64]


def test_a_linear_problem_is_solved_by_its_first_gauss_newton_step() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(500, 6)) * np.array([1e-3, 1.0, 10.0, 1e3, 0.1, 5.0])
    b = rng.normal(size=500)
    fit = levenberg_marquardt(lambda x: a @ x - b, lambda x: a, np.zeros(6))
    expected, *_ = np.linalg.lstsq(a, b, rcond=None)
    assert fit.converged
    assert fit.njev <= 2
    np.testing.assert_allclose(fit.x, expected, rtol=1e-9)
    assert fit.cost == pytest.approx(0.5 * float(np.sum((a @ expected - b) ** 2)), rel=1e-12)


def _rosenbrock(x: F64) -> F64:
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def _rosenbrock_jac(x: F64) -> F64:
    return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])


def test_the_rosenbrock_valley_is_followed_to_its_minimum() -> None:
    # Gauss–Newton steps fail here: the damping must engage and then let go
    fit = levenberg_marquardt(_rosenbrock, _rosenbrock_jac, np.array([-1.2, 1.0]))
    assert fit.converged
    np.testing.assert_allclose(fit.x, [1.0, 1.0], atol=1e-8)
    assert fit.cost < 1e-20


def _decay(t: F64, y: F64) -> tuple[Callable[[F64], F64], Callable[[F64], F64]]:
    def fun(p: F64) -> F64:
        return p[0] * np.exp(-p[1] * t) * np.cos(p[2] * t + p[3]) + p[4] - y

    def jac(p: F64) -> F64:
        e, arg = np.exp(-p[1] * t), p[2] * t + p[3]
        return np.column_stack([e * np.cos(arg), -t * p[0] * e * np.cos(arg),
                                -t * p[0] * e * np.sin(arg), -p[0] * e * np.sin(arg),
                                np.ones_like(t)])
    return fun, jac


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_noisy_nonlinear_fit_agrees_with_minpack(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 10.0, 4000)
    truth = np.array([3.0, 0.2, 2.0, 0.5, 1.0])
    fun, jac = _decay(t, np.zeros_like(t))
    y = fun(truth) + rng.normal(0.0, 0.05, t.size)
    fun, jac = _decay(t, y)
    start = truth * (1.0 + 0.05 * rng.normal(size=5))
    ours = levenberg_marquardt(fun, jac, start)
    ref = least_squares(fun, start, jac=jac, method="lm", x_scale="jac")
    assert ours.converged and ref.success
    np.testing.assert_allclose(ours.x, ref.x, rtol=1e-7)
    assert ours.cost == pytest.approx(ref.cost, rel=1e-10)


def test_running_out_of_evaluations_is_reported_not_hidden() -> None:
    fit = levenberg_marquardt(_rosenbrock, _rosenbrock_jac, np.array([-1.2, 1.0]), max_nfev=3)
    assert not fit.converged
    assert fit.nfev <= 3
    # the best point so far, never a worse one than the start
    assert fit.cost <= 0.5 * float(np.sum(_rosenbrock(np.array([-1.2, 1.0])) ** 2))


@pytest.mark.parametrize(("x0", "fun", "jac", "name"), [
    (np.zeros((2, 1)), _rosenbrock, _rosenbrock_jac, "x0"),
    (np.array([np.nan, 1.0]), _rosenbrock, _rosenbrock_jac, "x0"),
    (np.zeros(3), lambda x: np.zeros(2), lambda x: np.zeros((2, 3)), "fun"),
    (np.zeros(2), lambda x: np.array([np.inf, 0.0]), _rosenbrock_jac, "fun"),
    (np.zeros(2), _rosenbrock, lambda x: np.zeros((3, 2)), "jac"),
])
def test_bad_arguments_raise_naming_them(x0: F64, fun: object, jac: object, name: str) -> None:
    with pytest.raises(ValueError, match=f"^{name}:"):
        levenberg_marquardt(fun, jac, x0)  # type: ignore[arg-type]


def test_max_nfev_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="^max_nfev:"):
        levenberg_marquardt(_rosenbrock, _rosenbrock_jac, np.zeros(2), max_nfev=0)
