"""The change reference on disk: its calibration σ (σ_model) is kept across a restart."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.service.change import Reference, ReferenceStore


def _reference(with_model: bool) -> Reference:
    rng = np.random.default_rng(3)
    depth = rng.uniform(0, 20, (30, 40)).astype(np.float32)
    model = np.full((30, 40), 0.02, np.float32) if with_model else None
    return Reference(depth, np.full((30, 40), 0.05, np.float32),
                     rng.uniform(-5, 5, (30, 40, 3)).astype(np.float32), "2026-01-01T00:00:00",
                     {"kind": "upload"}, "cal-1", model)


def test_the_reference_with_its_sigma_model_survives_a_restart(tmp_path: Path) -> None:
    ReferenceStore(tmp_path).set(_reference(True))
    back = ReferenceStore(tmp_path).reference  # a new store: what the next start reads
    assert back is not None and back.sigma_model is not None
    np.testing.assert_array_equal(back.sigma_model, np.full((30, 40), 0.02, np.float32))
    np.testing.assert_array_equal(back.depth, _reference(True).depth)


def test_a_reference_without_sigma_model_still_loads(tmp_path: Path) -> None:
    ReferenceStore(tmp_path).set(_reference(False))
    back = ReferenceStore(tmp_path).reference
    assert back is not None and back.sigma_model is None and back.calibration == "cal-1"
