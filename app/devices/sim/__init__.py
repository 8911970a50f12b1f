"""The digital twin: simulated camera, projector and controller over a physically based scene.

Public API (other modules code against these names)::

    list_scenes() -> list[str]
    SimRig, default_rig(distortion=True); ideal_calibration(rig, schedule) (test oracle, ideal.py)
    RIG_NAMES, rig_by_name(name, distortion=True), endoscope_rig(distortion=True)  (rig presets)
    projector_defect_rig(rig, radial, gamma); rig_by_name("<preset>-projector-defect")
    SimulatedCamera, SimulatedProjector, SimulatedController, SimulatedWorld
    create_sim_devices(*, scene, seed, bit_depth, drop_rate, timeout_rate, disconnect_every_s,
                       realtime, distortion) -> SimDevices(camera, projector, controller, world)
    render_capture_set(scene, ..., rig="default") -> (CaptureSet, truth_depth, truth_points)
    instrument_exposure(scene, *, seed, rig, ...) -> the instrument's auto-exposure choice
    simulate_calibration_folder(out_dir, *, board, poses, seed, bit_depth, rig,
                                partial_boards) -> Path
"""

from app.devices.sim.devices import (
    SimDevices,
    SimulatedCamera,
    SimulatedController,
    SimulatedProjector,
    create_sim_devices,
)
from app.devices.sim.offline import (
    instrument_exposure,
    render_capture_set,
    simulate_calibration_folder,
)
from app.devices.sim.optics import (
    RIG_NAMES,
    SimRig,
    default_rig,
    endoscope_rig,
    projector_defect_rig,
    rig_by_name,
)
from app.devices.sim.scenes import list_scenes, sim_board
from app.devices.sim.world import READOUT_MS, SimulatedWorld

__all__ = [
    "READOUT_MS", "RIG_NAMES", "SimDevices", "SimRig", "SimulatedCamera", "SimulatedController",
    "endoscope_rig", "projector_defect_rig", "rig_by_name",
    "SimulatedProjector", "SimulatedWorld", "create_sim_devices", "default_rig", "list_scenes",
    "instrument_exposure", "render_capture_set", "sim_board", "simulate_calibration_folder",
]
