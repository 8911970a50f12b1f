"""The physical checks of a calibration, the dry-run rule and the valid-fraction watch."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from app.calib.calibration import save_calibration
from app.config import Settings
from app.core.calibration import Calibration
from app.core.schedule import PatternSchedule
from app.devices.sim import default_rig
from app.devices.sim.ideal import ideal_calibration
from app.service.calibration_checks import (
    MIN_REFERENCE_FRACTION,
    ValidFractionWatch,
    check_physical,
    dry_run_problem,
)
from app.service.calibrations import CalibrationManager
from app.service.pipeline import LivePipeline, PipelineConfig


@pytest.fixture(scope="module")
def good() -> dict[str, Any]:
    """A geometric-model calibration file of the simulated rig, with held-out figures."""
    cal = ideal_calibration(default_rig(distortion=False))
    data = cal.to_dict()
    data["held_out"] = {data["model"]["name"]: {"rms_mm": 0.04, "max_mm": 0.3, "noise_mm": 0.04,
                                                "systematic_mm": 0.01, "correlation_mm": 0.5}}
    data["pose_residuals"] = [{"pose": 0, "rms_mm": 0.03, "reprojection_px": 0.2, "points": 54}]
    return data


@pytest.fixture(scope="module")
def geometric(good: dict[str, Any]) -> dict[str, Any]:
    """The same with the geometric model (projector as an inverse camera; the simulator's fit)."""
    data = copy.deepcopy(good)
    data["model"] = {
        "name": "geometric",
        "rvec": [0.0, 0.2096, 0.0],
        "t_mm": [-5.87, 0.0, 1.25],
        "focal_px": 499.96,
        "principal_px": 303.4,
        "k1": 0.0,
        "projector_width_px": 608,
        "fringes": 36,
        "supported_region": good["model"]["supported_region"],
    }
    data["held_out"] = {"geometric": good["held_out"][good["model"]["name"]]}
    return data


def _changed(data: dict[str, Any], change: Callable[[dict[str, Any]], None]) -> Calibration:
    bad = copy.deepcopy(data)
    change(bad)
    return Calibration.from_dict(json.loads(json.dumps(bad)))


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(d: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        for key in parents:
            d = d[int(key)] if key.isdigit() else d[key]  # type: ignore[index]
        d[int(last) if last.isdigit() else last] = value  # type: ignore[index]
    return change


def test_the_simulated_rig_passes(good: dict[str, Any]) -> None:
    check_physical(Calibration.from_dict(good), PatternSchedule())


@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda d: d["camera_matrix"][0].__setitem__(0, 0.0),
            "camera_matrix: focal lengths must be positive",
        ),
        (lambda d: d["camera_matrix"][1].__setitem__(1, -1650.0), "fy=-1650"),
        (lambda d: d["camera_matrix"][0].__setitem__(2, 5000.0), "principal point (5000"),
        (lambda d: d["camera_matrix"][2].__setitem__(2, 2.0), "camera_matrix: must be"),
        (_set("reference_plane.offset_mm", -5.0), "reference_plane.offset_mm"),
        (
            _set("model.supported_region.phase_rad", [float("nan"), float("nan")]),
            "model.supported_region.phase_rad: need finite lo < hi",
        ),
        (_set("model.supported_region.phase_rad", [3.0, 3.0]), "model.supported_region.phase_rad"),
        (
            lambda d: d["held_out"][d["model"]["name"]].__setitem__("systematic_mm", 1e6),
            "systematic_mm: must be finite and within 0-",
        ),
        (lambda d: d["held_out"][d["model"]["name"]].__setitem__("rms_mm", -0.1), "rms_mm"),
        (
            lambda d: d["held_out"][d["model"]["name"]].__setitem__("correlation_mm", 1e9),
            "correlation_mm",
        ),
        (
            lambda d: d["pose_residuals"][0].__setitem__("reprojection_px", 1e4),
            "pose_residuals[0].reprojection_px",
        ),
    ],
)
def test_corruptions_are_refused_naming_the_field(
    good: dict[str, Any], change: Any, message: str
) -> None:
    cal = _changed(good, change)
    with pytest.raises(ValueError) as err:
        check_physical(cal, PatternSchedule())
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("change, message", [
    (_set("model.focal_px", -500.0), "model.focal_px: must be positive"),
    (_set("model.projector_width_px", 912), "model.projector_width_px: 912 differs"),
    (_set("model.fringes", 12), "model.fringes: 12 differs"),
    (_set("model.k1", float("inf")), "k1"),
])
def test_geometric_model_corruptions(geometric: dict[str, Any], change: Any, message: str) -> None:
    check_physical(Calibration.from_dict(geometric), PatternSchedule())
    try:
        cal = _changed(geometric, change)
    except ValueError as exc:  # some are refused already when the file is read
        assert message in str(exc)
        return
    with pytest.raises(ValueError) as err:
        check_physical(cal, PatternSchedule())
    assert message in str(err.value)


def test_an_empty_region_grid_is_refused(good: dict[str, Any]) -> None:
    cal = Calibration.from_dict(good)
    region = cal.model.region
    import numpy as np

    region.height_grid_mm = np.tile(np.array([5.0, 1.0]), (2, 2, 1))  # lo > hi everywhere: no data
    with pytest.raises(ValueError, match="no cell has data"):
        check_physical(cal, PatternSchedule())
    region.height_grid_mm = np.full((2, 2, 2), np.nan)
    with pytest.raises(ValueError, match="height_grid_mm: contains NaN"):
        check_physical(cal, PatternSchedule())


def test_another_schedule_is_refused(good: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="pattern: .*differs from the calibration"):
        check_physical(Calibration.from_dict(good), PatternSchedule(frequencies=(1, 8, 32)))


def test_dry_run_rule() -> None:
    assert dry_run_problem(0.55, 0.6, "sim") is None
    assert dry_run_problem(0.31, 0.6, "sim") is None  # above half
    reason = dry_run_problem(0.0, 0.6, "sim")
    assert (
        reason is not None
        and "0.0% of pixels valid against 60.0%" in reason
        and "force=true" in reason
    )
    # nothing to compare with
    assert dry_run_problem(0.0, MIN_REFERENCE_FRACTION / 2, "sim") is None
    with pytest.raises(ValueError, match="candidate_fraction"):
        dry_run_problem(1.5, 0.5, "sim")


def test_valid_fraction_watch() -> None:
    watch = ValidFractionWatch()
    for seq, f in enumerate((0.6, 0.61, 0.59), start=1):
        watch.observe(seq, f)
    assert watch.warning() is None  # no change yet
    watch.changed("activating calibration 'x'")
    watch.observe(4, 0.05)
    assert watch.warning() is None  # one result is not yet a level
    watch.observe(4, 0.05)  # the same result again: ignored
    assert watch.warning() is None
    watch.observe(5, 0.04)
    warning = watch.warning()
    assert (
        warning is not None
        and "collapsed from 60.0% to 4.5% after activating calibration 'x'" in warning
    )
    for seq in (6, 7, 8):
        watch.observe(seq, 0.58)
    assert watch.warning() is None  # recovered
    with pytest.raises(ValueError, match="ratio"):
        ValidFractionWatch(ratio=1.5)


def test_a_corrupted_active_calibration_is_refused_at_start(
    tmp_path: Path, good: dict[str, Any]
) -> None:
    folder = tmp_path / "calibrations"
    folder.mkdir()
    save_calibration(
        _changed(good, lambda d: d["camera_matrix"][0].__setitem__(0, 0.0)), folder / "active.json"
    )
    config = PipelineConfig(
        exposure_ms=20.0, led="green", bit_depth=8, rolling=False, autostart=False
    )
    mgr = CalibrationManager(
        Settings(data_dir=tmp_path, camera="opencv"), LivePipeline(config, PatternSchedule(), None)
    )
    mgr.load_initial(is_sim=False)
    assert mgr.calibration is None and not mgr.pipeline.has_engine
    assert mgr.last_error is not None and "focal lengths must be positive" in mgr.last_error
    assert any("focal lengths" in w for w in mgr.warnings)
