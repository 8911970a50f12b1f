"""A live result's σ parts: evaluated once per result, afresh when its arrays are replaced."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from app.recon.model_sigma import DEGREE, ModelSigmaTable
from app.recon.reconstructor import split_noise
from app.service.reconstruction import LiveResult

H, W = 40, 56


def _table() -> ModelSigmaTable:
    """σ_model² = 0.0004 + 0.0002·x mm² (x the normalised height): 20–24 µm over the volume."""
    coefs = np.zeros((1, DEGREE + 1, W), np.float32)
    coefs[0, 0] = 4e-4
    coefs[0, 1] = 2e-4
    return ModelSigmaTable(coefs, np.zeros(H, np.int64), np.zeros(H, np.float32), mid_mm=10.0,
                           inv_half_mm=0.1)


def _result(depth: np.ndarray, sigma: np.ndarray | None,
            table: ModelSigmaTable | None) -> LiveResult:
    now = time.monotonic()
    return LiveResult(depth=depth, points=np.zeros((H, W, 3), np.float32),
                      valid=np.isfinite(depth), reason=np.zeros((H, W), np.uint8),
                      texture=np.zeros((H, W), np.float32),
                      modulation=np.zeros((H, W), np.float32), motion=None, mode="set",
                      frame_indices=[], timestamps=[], exposure_ms=30.0, led="green",
                      full_scale=255.0, received_s=now, published_s=now, recon_ms=1.0,
                      sigma=sigma, model_sigma=table)


def test_the_parts_are_computed_once_and_are_the_split_of_sigma() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0, 20, (H, W)).astype(np.float32)
    depth[3, :5] = np.nan
    sigma = rng.uniform(0.03, 0.08, (H, W)).astype(np.float32)
    sigma[3, :5] = np.nan
    table = _table()
    res = _result(depth, sigma, table)
    model = res.sigma_model
    assert model is not None and res.sigma_noise is not None
    np.testing.assert_array_equal(model, table.sigma_mm(depth))
    np.testing.assert_array_equal(res.sigma_noise, split_noise(sigma, table.sigma_mm(depth)))
    assert res.sigma_model is model and res.sigma_noise is res.sigma_noise  # kept
    with pytest.raises(ValueError, match="read-only"):
        model[0, 0] = 1.0  # a reader cannot change what the next one gets
    got: list[object] = []
    threads = [threading.Thread(target=lambda: got.append(res.sigma_noise)) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(g is res.sigma_noise for g in got)


def test_replacing_an_array_evaluates_the_parts_afresh() -> None:
    rng = np.random.default_rng(1)
    depth = rng.uniform(0, 20, (H, W)).astype(np.float32)
    sigma = np.full((H, W), 0.05, np.float32)
    table = _table()
    res = _result(depth, sigma, table)
    first_noise, first_model = res.sigma_noise, res.sigma_model
    # as exposure bracketing's fusion or an edit does: new arrays in the same result
    res.sigma = np.full((H, W), 0.08, np.float32)
    np.testing.assert_array_equal(res.sigma_noise, split_noise(res.sigma, table.sigma_mm(depth)))
    assert res.sigma_noise is not first_noise
    res.depth = depth + 5.0
    np.testing.assert_array_equal(res.sigma_model, table.sigma_mm(depth + 5.0))
    assert not np.array_equal(res.sigma_model, first_model)
    res.model_sigma = None  # a calibration without a jackknife: σ_model 0, σ_noise = σ
    assert res.sigma_model is not None and not res.sigma_model.any()
    np.testing.assert_array_equal(res.sigma_noise, res.sigma)
    res.sigma = None
    assert res.sigma_model is None and res.sigma_noise is None
