"""The Eq. (5) model against the closed-form rig; singular denominators; the volume test."""

from __future__ import annotations

import numpy as np

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon.model import (
    SINGULAR_RTOL,
    calibration_model_tables,
    evaluate_height,
    model_tables,
    outside_volume,
    row_coefficients,
)


def test_closed_form_rig_depth_is_exact():
    rig = Rig()
    cal = rig.calibration()
    tables = calibration_model_tables(cal)
    for h in (
        bump_surface(rig),
        np.zeros((rig.height, rig.width)),
        np.full((rig.height, rig.width), 30.0),
    ):
        height, singular = evaluate_height(tables, rig.finest_phase(h))
        assert not singular.any()
        assert np.max(np.abs(height - h)) < 1e-9  # mm, ≪ 1e-3


def test_rig_coefficients_have_eq5_structure():
    num, den = Rig().coefficients()
    assert num.shape == (11,) and den.shape == (12,)
    assert np.all(num[5:] == 0) and np.all(den[6:] == 0)  # the rig is exactly bilinear


def test_tables_match_direct_evaluation_of_eq5():
    rng = np.random.default_rng(3)
    c, d = rng.normal(size=11), rng.normal(size=12)
    d[0] = 5.0
    norm = {"u": (10.0, 7.0), "v": (5.0, 4.0), "phi": (100.0, 50.0)}
    t = model_tables(c, d, norm, (21, 11))
    phi = rng.uniform(0, 200, (11, 21))
    uu, vv = np.meshgrid((np.arange(21) - 10.0) / 7.0, (np.arange(11) - 5.0) / 4.0)
    p = (phi - 100.0) / 50.0
    terms = [np.ones_like(uu), uu, vv, uu**2, vv**2, uu * vv]
    num = 1 + c[0] * p + sum((c[1 + 2 * i] + c[2 + 2 * i] * p) * terms[i + 1] for i in range(5))
    den = d[0] + d[1] * p + sum((d[2 + 2 * i] + d[3 + 2 * i] * p) * terms[i + 1] for i in range(5))
    height, _ = evaluate_height(t, phi)
    assert np.allclose(height, num / den, rtol=1e-12, atol=1e-12)
    assert model_tables(c, d, norm, (21, 11), dtype=np.float32).a0.dtype == np.float32


def test_singular_denominator_flagged():
    d = np.zeros(12)
    d[2] = 1.0  # denominator = u', zero on the column u = u0
    norm = {"u": (4.0, 4.0), "v": (2.0, 2.0), "phi": (0.0, 1.0)}
    t = model_tables(np.zeros(11), d, norm, (9, 5))
    _, singular = evaluate_height(t, np.ones((5, 9)))
    assert singular[:, 4].all() and singular.sum() == 5
    assert SINGULAR_RTOL < 1e-3


def test_outside_volume_with_margin_and_nan():
    h = np.array([-2.5, -1.5, 0.0, 31.9, 32.1, np.nan, np.inf])
    assert outside_volume(h, (0.0, 30.0), 2.0).tolist() == [
        True,
        False,
        False,
        False,
        True,
        True,
        True,
    ]


def test_row_coefficients_reproduce_the_tables():
    rng = np.random.default_rng(4)
    c, d = rng.normal(size=11), rng.normal(size=12)
    norm = {"u": (10.0, 7.0), "v": (5.0, 4.0), "phi": (100.0, 50.0)}
    t = model_tables(c, d, norm, (21, 11))
    rows = row_coefficients(c, d, norm, (21, 11))
    assert (
        rows.u_norm.shape == (21,)
        and rows.coefs.shape == (11, 12)
        and rows.coefs.dtype == np.float32
    )
    x = rows.u_norm.astype(np.float64)
    k = rows.coefs.astype(np.float64)
    for i, table in enumerate((t.a0, t.a1, t.b0, t.b1)):
        alpha, beta, gamma = (k[:, 3 * i + j, None] for j in range(3))
        assert np.allclose(alpha + beta * x + gamma * x**2, table, rtol=1e-6, atol=1e-6)
    assert (rows.phi0, rows.inv_sphi) == (t.phi0, t.inv_sphi)
