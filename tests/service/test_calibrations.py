"""The calibration manager: activation installs the live engine, checks, summary, the store."""

from __future__ import annotations

import dataclasses

import pytest

from app.config import Settings
from app.core.errors import Conflict
from app.core.schedule import PatternSchedule
from app.devices.sim import default_rig
from app.devices.sim.ideal import ideal_calibration
from app.service.calibrations import CalibrationManager
from app.service.pipeline import LivePipeline, PipelineConfig


@pytest.fixture(scope="module")
def calibration():
    return ideal_calibration(default_rig(distortion=False))


def _manager(tmp_path) -> CalibrationManager:
    config = PipelineConfig(
        exposure_ms=20.0, led="green", bit_depth=8, rolling=False, autostart=False
    )
    return CalibrationManager(
        Settings(data_dir=tmp_path), LivePipeline(config, PatternSchedule(), None)
    )


def test_activation_installs_the_engine_and_summarises(tmp_path, calibration):
    mgr = _manager(tmp_path)
    assert mgr.summary() is None and not mgr.pipeline.has_engine
    why = mgr.pipeline.why_no_result()
    assert isinstance(why, Conflict) and why.detail == "no depth result: no calibration is active"
    mgr.activate(calibration, name="bench", persist=True)
    assert mgr.pipeline.has_engine and mgr.calibration is calibration
    s = mgr.summary()
    assert s is not None and (s.name, s.image_size, s.poses) == (
        "bench",
        tuple(calibration.image_size),
        0,
    )
    assert s.to_dict()["height_range_mm"] == list(calibration.height_range_mm)
    assert (tmp_path / "calibrations" / "active.json").is_file()
    assert (tmp_path / "calibrations" / "bench.json").is_file()


def test_activation_rejects_another_schedule(tmp_path, calibration):
    mgr = _manager(tmp_path)
    other = dataclasses.replace(calibration, pattern=PatternSchedule(frequencies=(1, 8, 32)))
    with pytest.raises(ValueError, match="differs from the calibration"):
        mgr.activate(other, name="x", persist=False)
    assert mgr.calibration is None and not mgr.pipeline.has_engine


def test_conflict_without_calibration_or_session(tmp_path):
    mgr = _manager(tmp_path)
    with pytest.raises(Conflict, match="no calibration session"):
        mgr.require_session()
    session = mgr.start_session({"type": "checkerboard", "inner_corners": [9, 6], "square_mm": 2.0})
    assert mgr.require_session() is session and session.board.pitch_mm == 2.0
    with pytest.raises(Conflict, match="solved"):
        mgr.activate_session("x")
    with pytest.raises(Conflict, match="no calibration is active"):
        mgr.reconstruct(None)  # type: ignore[arg-type]  # refused before the set is looked at


@pytest.mark.parametrize("max_sigma_mm, gross_error_mm, expected", [
    (None, 0.0, None), (0.05, 0.0, 0.05), (0.05, 0.5, 0.05), (None, 0.5, 0.5 / 4.891638),
    # the explicit setting replaces the tolerance's bound
    (None, 1.0, 1.0 / 4.891638), (1.0, 0.5, 1.0)])
def test_the_live_engine_carries_the_max_sigma_setting(
    tmp_path, calibration, max_sigma_mm, gross_error_mm, expected
):
    config = PipelineConfig(
        exposure_ms=20.0, led="green", bit_depth=8, rolling=False, autostart=False
    )
    mgr = CalibrationManager(
        Settings(data_dir=tmp_path, max_sigma_mm=max_sigma_mm, gross_error_mm=gross_error_mm),
        LivePipeline(config, PatternSchedule(), None),
    )
    assert mgr.engine_for(PatternSchedule()) == (None, None)  # nothing active yet
    mgr.activate(calibration, name="s", persist=False)
    engine, why = mgr.engine_for(PatternSchedule())
    assert why is None and engine is not None
    assert engine.sigma_limit_mm == (
        None if expected is None else pytest.approx(expected, rel=1e-6)
    )


@pytest.mark.parametrize("min_modulation", [None, 5.1])
def test_the_live_engine_carries_the_min_modulation_setting(tmp_path, calibration, min_modulation):
    config = PipelineConfig(
        exposure_ms=20.0, led="green", bit_depth=8, rolling=False, autostart=False
    )
    mgr = CalibrationManager(Settings(data_dir=tmp_path, min_modulation=min_modulation),
                             LivePipeline(config, PatternSchedule(), None))
    mgr.activate(calibration, name="s", persist=False)
    engine, why = mgr.engine_for(PatternSchedule())
    assert why is None and engine is not None and engine.min_modulation == min_modulation
    with pytest.raises(ValueError, match="min_modulation"):
        Settings(min_modulation=-1)


def test_max_sigma_setting_is_validated():
    with pytest.raises(ValueError, match="max_sigma_mm"):
        Settings(max_sigma_mm=0)


def test_gross_error_setting_is_validated_and_read_from_the_environment(monkeypatch, tmp_path):
    with pytest.raises(ValueError, match="gross_error_mm"):
        Settings(data_dir=tmp_path, gross_error_mm=-0.1)
    monkeypatch.setenv("FRINGESCOPE_GROSS_ERROR_MM", "0")
    assert Settings(data_dir=tmp_path).gross_error_mm == 0.0
