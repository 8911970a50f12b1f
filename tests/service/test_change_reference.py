"""The change reference on disk: its calibration σ (σ_model) is kept across a restart."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

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


def test_a_fault_in_one_comparison_does_not_end_the_change_thread(
    tmp_path: Path, sim_calibration_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import app.service.change as change_module
    from app.service.calibration_store import load
    from app.service.change import ChangeService
    from app.service.reconstruction import LiveResult

    cal = load(sim_calibration_file)
    service = ChangeService(tmp_path / "ref", lambda: cal)
    rng = np.random.default_rng(5)
    depth = rng.uniform(5, 10, (30, 40)).astype(np.float32)
    sigma = np.full((30, 40), 0.05, np.float32)
    points = rng.uniform(-5, 5, (30, 40, 3)).astype(np.float32)
    service.set_reference(depth, sigma, points, {"kind": "test"})

    real_compare, calls = change_module.compare, []

    def compare_failing_once(*args: object, **kwargs: object) -> object:
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("injected fault")
        return real_compare(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(change_module, "compare", compare_failing_once)

    def result(seq: int) -> LiveResult:
        return LiveResult(
            depth=depth, points=points, valid=np.isfinite(depth),
            reason=np.zeros((30, 40), np.uint8), texture=depth, modulation=depth, motion=None,
            mode="set", frame_indices=[], timestamps=[], exposure_ms=20.0, led="green",
            full_scale=255.0, received_s=0.0, published_s=0.0, recon_ms=1.0, seq=seq,
            sigma=sigma,
        )

    service.start()
    try:
        service.on_map(1, result(1))
        deadline = time.monotonic() + 30
        while service.last_error is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert service.last_error is not None and "injected fault" in service.last_error
        service.on_map(2, result(2))
        while service.slot.latest()[1] is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert all(t.is_alive() for t in service.threads())
        assert service.slot.latest()[1] is not None  # the next map was compared
    finally:
        service.close(5.0)
