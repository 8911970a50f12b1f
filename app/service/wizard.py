"""The calibration wizard on the live instrument: the next pose, and the twin's board.

The session itself (its poses, coverage and solve) is the calibration manager's
(:mod:`app.service.calibrations`); this part adds what the wizard does to the live view: on
the simulator the board moves to the suggested pose (and the exposure follows it), and the
configured scene comes back when the session ends, cancelled or activated.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any

import numpy as np

from app.config import Settings
from app.devices.sim.offline import auto_exposure_ms, simulate_calibration_folder
from app.devices.sim.optics import rig_by_name
from app.devices.sim.scenes import board_poses, board_scene
from app.service.calibration_session import CalibrationSession, advice_dict, twin_board_pose
from app.service.calibrations import CalibrationManager
from app.service.pipeline import LivePipeline

__all__ = ["CalibrationWizard", "sim_calibration_poses"]


@functools.cache
def sim_calibration_poses() -> int:
    """Board poses the simulator's first-start calibration simulates (its writer's default)."""
    default = inspect.signature(simulate_calibration_folder).parameters["poses"].default
    return int(default)


class CalibrationWizard:
    """The REST wizard's steps that act on the live view.

    Args:
        settings: the instrument's settings (the twin's rig and scene, the bit depth).
        pipeline: the live pipeline (its devices: the twin's world, if any).
        calibrations: the calibration manager that holds the session.
        set_exposure: how the instrument changes the exposure (ms in, ms set out), so the
            change is recorded as any other.
    """

    def __init__(self, settings: Settings, pipeline: LivePipeline,
                 calibrations: CalibrationManager,
                 set_exposure: Callable[[float], float]) -> None:
        self.settings = settings
        self.pipeline = pipeline
        self.calibrations = calibrations
        self._set_exposure = set_exposure
        self._twin_scene_moved = False  # the wizard put the twin's board in view

    def suggest_pose(self) -> dict[str, Any]:
        """Where to hold the board for the session's next pose; the twin puts its board there.

        Pose 0 is the reference plane (flat, the farthest); after it the session's coverage
        (:mod:`app.calib.coverage`) names the image region, height and tilts that add most
        calibrated cells. On the twin the board (the session's spec) moves there and the
        exposure is set for it; on hardware the answer is the advice alone. ``of`` is the
        simulator's calibration series length, the poses planned at least.
        """
        session = self.calibrations.require_session()
        devices = self.pipeline.devices
        world = devices.world if devices is not None else None
        rig = world.rig if world is not None else rig_by_name(self.settings.sim_rig)
        planned = sim_calibration_poses()
        k = sum(1 for p in session.poses if p.found)
        _, advice = session.coverage()
        if k == 0:  # the reference plane, where the simulator's own calibration puts it
            pose = board_poses(rig, planned, seed=0)[0]
        else:
            pose = twin_board_pose(rig, session.board, advice)
        origin, axes = pose
        ref = rig.reference
        height_mm = float(ref.normal @ origin + ref.offset_mm)
        cos_tilt = abs(float(axes[:, 2] @ ref.normal))  # axes: columns e_s, e_t, normal
        tilt_deg = float(np.degrees(np.arccos(min(cos_tilt, 1.0))))
        exposure_ms = None
        if world is not None:
            world.set_scene(board_scene(rig, session.board, pose))
            self._twin_scene_moved = True
            exposure_ms = round(auto_exposure_ms(world, led=world.led, current=world.current,
                                                 bits=self.settings.bit_depth), 2)
            self._set_exposure(exposure_ms)
        return {"index": k, "of": max(planned, k + 1), "height_mm": round(height_mm, 2),
                "tilt_deg": round(tilt_deg, 1), "moved": world is not None,
                "exposure_ms": exposure_ms,
                "hint": f"pose {k} of {max(planned, k + 1)}: the whole board in view; "
                        f"{advice.text}",
                "suggestion": advice_dict(advice), "coverage": session.coverage_dict()}

    def cancel_session(self) -> CalibrationSession | None:
        """End the session without a calibration (the one ended, or None)."""
        session = self.calibrations.cancel_session()
        self._restore_twin_scene()
        return session

    def activate_session(self, name: str, *, force: bool = False) -> dict[str, Any]:
        """Check and activate the session's calibration (its summary); the twin's scene back."""
        summary = self.calibrations.activate_session(name, force=force).to_dict()
        self._restore_twin_scene()
        return summary

    def _restore_twin_scene(self) -> None:
        """After the session: the twin shows its configured scene again."""
        devices = self.pipeline.devices
        world = devices.world if devices is not None else None
        if world is not None and self._twin_scene_moved:
            self._twin_scene_moved = False
            world.set_scene(self.settings.sim_scene)
