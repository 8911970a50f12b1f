"""Printed and metrology scenes: calibration boards, the 45° depth-of-field
target, plane, spheres."""

from __future__ import annotations

import numpy as np

from app.core.board import BoardSpec, BoardType
from app.devices.sim.optics import SimRig, rotation_x, rotation_y
from app.devices.sim.scenes.base import (
    F64,
    HeightField,
    PrintFn,
    Scene,
    Sphere,
    flat_field,
    frame_from_normal,
)
from app.devices.sim.shading_kernels import checker_reflectance

BLACK = 0.07  # printed black relative to the paper's white


#: the board types the simulator prints
SIM_BOARD_TYPES: dict[str, BoardType] = {"checkerboard": "checkerboard", "circles": "circles"}


def sim_board(board_type: str = "checkerboard") -> BoardSpec:
    """The simulator's board of ``board_type`` (``checkerboard`` or ``circles``, a symmetric grid of
    dark dots).

    108 corners over 15 × 11 mm: twice the corners of an 8 × 6 board of the same size
    halve the variance of each pose — and pose 0 *is* the reference plane.
    """
    if board_type not in SIM_BOARD_TYPES:
        raise ValueError(f"board: must be 'checkerboard' or 'circles', got {board_type!r}")
    return BoardSpec(SIM_BOARD_TYPES[board_type], 12, 9, 1.4)


def board_points_mm(spec: BoardSpec) -> F64:
    """(cols·rows, 3) control points in the sim's board coordinates (s, t, 0), centred,
    row-major from the top-left."""
    s = (np.arange(spec.cols) - (spec.cols - 1) / 2) * spec.pitch_mm
    t = (np.arange(spec.rows) - (spec.rows - 1) / 2) * spec.pitch_mm
    ss, tt = np.meshgrid(s, t)
    return np.stack([ss.ravel(), tt.ravel(), np.zeros(ss.size)], -1)


def board_printer(spec: BoardSpec) -> PrintFn:
    """The board's print: reflectance at board coordinates (s, t), mm."""
    cols, rows = spec.cols, spec.rows
    p = spec.pitch_mm
    if spec.type == "checkerboard":
        half_s, half_t = (cols + 1) * p / 2, (rows + 1) * p / 2

        def checker(s: F64, t: F64) -> F64:
            # one compiled pass (the numpy expression made six temporaries: 25 ms a call)
            ss, tt = np.broadcast_arrays(np.asarray(s, np.float64), np.asarray(t, np.float64))
            out = np.empty(ss.shape)
            checker_reflectance(np.ascontiguousarray(ss).reshape(-1),
                                np.ascontiguousarray(tt).reshape(-1), half_s, half_t, p, BLACK,
                                out.reshape(-1))
            return out

        return checker
    if spec.type != "circles":
        raise ValueError(f"board: unknown type {spec.type!r}")
    r = 0.25 * p

    def circles(s: F64, t: F64) -> F64:
        i = np.clip(np.rint(s / p + (cols - 1) / 2), 0, cols - 1)
        j = np.clip(np.rint(t / p + (rows - 1) / 2), 0, rows - 1)
        cs, ct = (i - (cols - 1) / 2) * p, (j - (rows - 1) / 2) * p
        return np.where((s - cs) ** 2 + (t - ct) ** 2 < r * r, BLACK, 1.0)

    return circles


def board_poses(rig: SimRig, poses: int, seed: int | None = 0) -> list[tuple[F64, F64]]:
    """(origin, axes) of each board pose; pose 0 is the rig's reference plane itself.

    Later poses step toward the scope up to ~18 mm above the reference, tilted by about
    ±30° about both axes and shifted a little, so the corners stay in view. Strong tilts
    separate the focal length from the distance; with ±10° the focal length was off by
    up to 1.2 px (7e-4), which scales every height and moved the reference plane by
    0.03 mm — a mean depth error of up to 0.011 mm on the DOF target.
    """
    if poses < 2:
        raise ValueError(f"poses: need at least 2, got {poses}")
    rng = np.random.default_rng(seed)
    ref = rig.reference
    out = [frame_from_normal(rig.reference_point_mm, ref.normal)]
    heights = np.linspace(3.0, 18.0, poses - 1)
    for k, h in enumerate(heights):
        tilt_x = (28.0 if k % 2 == 0 else -28.0) + rng.uniform(-4, 4)
        tilt_y = (-30.0 if (k // 2) % 2 == 0 else 30.0) + rng.uniform(-3, 3)
        normal = rotation_x(tilt_x) @ rotation_y(tilt_y) @ ref.normal
        axis = np.array([0.0, 0.0, 1.0])
        t_ax = (h - ref.offset_mm) / (ref.normal @ axis)
        shift = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), 0.0])
        out.append(frame_from_normal(t_ax * axis + shift, normal))
    return out


def board_scene(rig: SimRig, spec: BoardSpec, pose: tuple[F64, F64], *,
                paper_half_mm: float = 11.0) -> Scene:
    """The board printed on white paper (a square of side 2·paper_half_mm) at ``pose``."""
    origin, axes = pose
    return Scene(f"board_{spec.type}",
                 flat_field(origin, axes, paper_half_mm, "white", board_printer(spec), ds=1.0),
                 description="calibration board")


def plane_scene(rig: SimRig) -> Scene:
    """A matte grey plane 10 mm above the reference, tilted 15° about the camera x axis."""
    return _tilted_plane(rig, "plane", 10.0, 15.0, 25.0, "metrology plane")


def far_plane_scene(rig: SimRig) -> Scene:
    """A matte grey plane 6 mm below the reference (≈ 46 mm from the scope), tilted 30°:
    it crosses the far end of the calibrated volume, for the out-of-volume checks."""
    return _tilted_plane(rig, "far_plane", -6.0, 30.0, 30.0, "plane beyond the calibrated volume")


def _tilted_plane(rig: SimRig, name: str, height_mm: float, tilt_deg: float, half_size_mm: float,
                  description: str) -> Scene:
    ref = rig.reference
    normal = rotation_x(tilt_deg) @ ref.normal
    z = (height_mm - ref.offset_mm) / ref.normal[2]
    origin, axes = frame_from_normal(np.array([0.0, 0.0, z]), normal)
    return Scene(name, flat_field(origin, axes, half_size_mm, "grey", ds=1.0),
                 description=description)


def ruler_printer() -> PrintFn:
    """Line-pair groups (0.5–4 lp/mm) in a strip and mm ticks along the incline (s)."""
    freqs = np.array([0.5, 1.0, 2.0, 3.0, 4.0])

    def ruler(s: F64, t: F64) -> F64:
        out = np.ones(np.broadcast(s, t).shape)
        # NaN s (no surface there) prints nothing; nan_to_num only keeps the cast defined
        group = np.floor((np.nan_to_num(s) + 20.0) / 4.0).astype(int) % len(freqs)
        f = freqs[group]
        bars = (t > 6.0) & (t < 9.0) & (((s + 20.0) * f) % 1.0 < 0.5)
        ticks = (t > 9.5) & (t < np.where(np.abs(s - np.rint(s / 5) * 5) < 0.5, 11.5, 10.5)) & \
            (np.abs(s - np.rint(s)) < 0.075)
        out[bars | ticks] = BLACK
        return out

    return ruler


def dof_target_field(rig: SimRig) -> tuple[F64, F64]:
    """Frame of the 45° incline: heights 0–20 mm above the reference across the view."""
    ref = rig.reference
    normal = rotation_y(-45.0) @ ref.normal
    z = (10.0 - ref.offset_mm) / ref.normal[2]
    return frame_from_normal(np.array([0.0, 0.0, z]), normal)


def dof_target_surface(rig: SimRig, ds: float = 0.1) -> HeightField:
    origin, axes = dof_target_field(rig)
    hf = flat_field(origin, axes, 16.0, "white", ruler_printer(), ds=ds)
    return hf


def dof_target_scene(rig: SimRig) -> Scene:
    return Scene("dof_target", dof_target_surface(rig, ds=1.0),
                 description="45° depth-of-field target with ruler")


def sphere_scene(rig: SimRig) -> Scene:
    """Two matte spheres (r = 4 mm, 12 mm apart) resting on a grey plate at the reference plane."""
    ref = rig.reference
    origin, axes = frame_from_normal(rig.reference_point_mm, ref.normal)
    spheres = [Sphere(origin + axes @ np.array([sx, 0.0, 4.0]), 4.0, "grey") for sx in (-6.0, 6.0)]
    return Scene("sphere", flat_field(origin, axes, 25.0, "white", ds=1.0), spheres,
                 description="ball bar: two spheres on a plate")
