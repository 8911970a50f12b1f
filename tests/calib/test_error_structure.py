"""app.calib.fitting.error_structure: held-out errors split into independent noise and a smooth
part."""

import numpy as np
import pytest

from app.calib.fitting import error_structure


def _poses(noise_mm, smooth_mm, length_mm, seed=0, poses=4, n=700):
    """Per pose: points on a 12 mm board at 60 mm and errors = iid noise + an
    exponential-covariance field."""
    rng = np.random.default_rng(seed)
    errors, points = [], []
    for _ in range(poses):
        xy = rng.uniform(0, 12, (n, 2))
        x = np.column_stack([xy, np.full(n, 60.0)])
        e = rng.normal(0, noise_mm, n)
        if smooth_mm > 0:
            d = np.linalg.norm(x[:, None] - x[None], axis=-1)
            c = smooth_mm**2 * np.exp(-d / length_mm) + 1e-12 * np.eye(n)
            e = e + np.linalg.cholesky(c) @ rng.normal(size=n)
        errors.append(e)
        points.append(x)
    return errors, points


def test_pure_noise_has_no_systematic_part():
    out = error_structure(*_poses(0.02, 0.0, 1.0))
    assert out["noise_mm"] == pytest.approx(0.02, rel=0.05)
    assert out["systematic_mm"] < 0.005


def test_recovers_noise_and_smooth_part():
    out = error_structure(*_poses(0.02, 0.015, 4.0, seed=1))
    assert out["noise_mm"] == pytest.approx(0.02, rel=0.1)
    assert out["systematic_mm"] == pytest.approx(0.015, rel=0.3)
    assert 1.5 < out["correlation_mm"] < 12.0


def test_needs_one_point_array_per_pose():
    with pytest.raises(ValueError, match="points"):
        error_structure([np.zeros(3)], [])
