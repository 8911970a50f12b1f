"""The simulator's scenes, by name."""

from __future__ import annotations

from collections.abc import Callable

from app.devices.sim.optics import SimRig
from app.devices.sim.scenes.base import HeightField, Scene, Sphere, Tool
from app.devices.sim.scenes.targets import (
    board_points_mm,
    board_poses,
    board_scene,
    dof_target_scene,
    far_plane_scene,
    plane_scene,
    sim_board,
    sphere_scene,
)
from app.devices.sim.scenes.tissue import (
    anastomosis_scene,
    breathing_scene,
    flap_scene,
    pile_scene,
    still_tissue_scene,
    tool_scene,
    with_bumps,
)

SCENES: dict[str, Callable[[SimRig], Scene]] = {
    "plane": plane_scene,
    "far_plane": far_plane_scene,
    "dof_target": dof_target_scene,
    "skin_flap": lambda rig: flap_scene(rig, "skin"),
    "intestine_flap": lambda rig: flap_scene(rig, "intestine"),
    "intestine_pile": pile_scene,
    "anastomosis": anastomosis_scene,
    "anastomosis_bright": lambda rig: anastomosis_scene(rig, suture="suture_bright"),
    "sphere": sphere_scene,
    "breathing": breathing_scene,
    "tool": tool_scene,
    "tissue_still": still_tissue_scene,
    # the still loops with a 0.3 mm bump 3 mm across: the change map's demonstration
    "tissue_bump": lambda rig: with_bumps(still_tissue_scene(rig), [(0.0, 0.0, 0.3, 3.0)],
                                          "tissue_bump"),
}


def list_scenes() -> list[str]:
    """Names accepted by :func:`build_scene` (calibration boards are made by ``board_scene``)."""
    return list(SCENES)


def build_scene(name: str, rig: SimRig) -> Scene:
    try:
        return SCENES[name](rig)
    except KeyError:
        raise ValueError(f"scene: unknown {name!r}; choose from {', '.join(SCENES)}") from None


__all__ = ["HeightField", "SCENES", "Scene", "Sphere", "Tool", "board_points_mm", "board_poses",
           "board_scene", "build_scene", "list_scenes", "sim_board"]
