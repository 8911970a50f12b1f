"""Where the instrument's calibrations live in the data folder, and the simulator's own.

``<data_dir>/calibrations/active.json`` is the calibration last activated by the user;
``sim.json`` the one created automatically for the simulator on first start.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

from app.calib.calibration import load_calibration, save_calibration
from app.config import Settings
from app.core.calibration import Calibration

log = logging.getLogger("fringescope.service.calibration")

#: extra key of a calibration file remembering the name it was activated under
NAME_KEY = "instrument_name"


def folder(settings: Settings) -> Path:
    return Path(settings.data_dir) / "calibrations"


def initial_path(settings: Settings) -> Path | None:
    """The calibration to load at start: the configured file, the active one, the simulator's."""
    if settings.calibration_file is not None:
        path = Path(settings.calibration_file)
        if not path.is_file():
            raise ValueError(f"{path}: calibration file not found")
        return path
    sim = settings.camera == "sim"
    for name in ("active.json", sim_file_name(settings)) if sim else ("active.json",):
        path = folder(settings) / name
        if path.is_file():
            return path
    return None


def load(path: Path) -> Calibration:
    return load_calibration(path)


def save_active(settings: Settings, cal: Calibration, name: str) -> Path:
    """Keep ``cal`` as ``<name>.json`` and as ``active.json`` (atomic writes)."""
    if not name.replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"name: only letters, digits, '-' and '_' allowed, got {name!r}")
    cal.extra[NAME_KEY] = name
    save_calibration(cal, folder(settings) / f"{name}.json")
    return save_calibration(cal, folder(settings) / "active.json")


#: prefix of the simulator calibration's temporary work folder inside the calibration folder
WORK_FOLDER_PREFIX = ".sim-calib-"


def sim_file_name(settings: Settings) -> str:
    """The simulator's own calibration file: ``sim.json`` for the default rig,
    ``sim-<rig>.json`` else."""
    return "sim.json" if settings.sim_rig == "default" else f"sim-{settings.sim_rig}.json"


def create_sim_calibration(settings: Settings) -> Calibration:
    """Simulate board poses of the configured rig, calibrate from them and store
    them (minutes at most)."""
    from app.calib.fitting import calibrate_folder
    from app.devices.sim import simulate_calibration_folder

    out = folder(settings)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=WORK_FOLDER_PREFIX, dir=out))
    try:
        log.info("creating the simulator's calibration in %s", work)
        simulate_calibration_folder(work / "poses", seed=settings.sim_seed, rig=settings.sim_rig)
        report = calibrate_folder(work / "poses")
        save_calibration(report.calibration, out / sim_file_name(settings))
        return report.calibration
    finally:
        shutil.rmtree(work, ignore_errors=True)
