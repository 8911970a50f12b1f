"""Acceptance helpers against analytic geometry."""

from __future__ import annotations

import numpy as np
import pytest

from app.analysis.acceptance import projector_incidence_cos


def _unit_sphere_points(theta: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)


def test_incidence_on_a_unit_sphere_lit_from_the_axis():
    d = 4.0  # projector on the +z axis, 4 radii from the centre
    theta = np.linspace(0.0, np.pi, 181)
    p = _unit_sphere_points(theta)
    got = projector_incidence_cos(p, p, [0.0, 0.0, d])
    want = (d * np.cos(theta) - 1.0) / np.sqrt(1.0 + d * d - 2.0 * d * np.cos(theta))
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert got[0] == pytest.approx(1.0)
    # the shadow line: the projector's rays touch the sphere where cos θ = 1/d
    assert np.all((got > 0) == (np.cos(theta) > 1.0 / d + 1e-12))


def test_lit_fraction_of_a_uniformly_sampled_sphere():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(200_000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = 5.0
    lit = projector_incidence_cos(n, n, [0.0, 0.0, d]) > 0
    assert lit.mean() == pytest.approx((1 - 1 / d) / 2, abs=0.005)  # spherical cap area


def test_bad_input_names_the_argument():
    p = np.zeros((4, 3))
    with pytest.raises(ValueError, match="normals"):
        projector_incidence_cos(p, np.zeros((4, 2)), [0, 0, 1])
    with pytest.raises(ValueError, match="projector_centre_mm"):
        projector_incidence_cos(p, p, [0, np.nan, 1])
