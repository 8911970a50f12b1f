"""Randomised rigs for the twin: robustness across rigs, not two presets.

:func:`random_rig` draws, from a seed, a camera (sensor size, focal length, principal-point
offset, barrel/pincushion k1 and k2 kept invertible over the image, bit depth 8/10/12), a
projector (triangulation angle, baseline, a focal length that lights the camera's field over the
working volume), a hand-placed reference plane, and a calibration board set (corner grid, how
far the board reaches from the image centre — the central third to the full field — and 6–16
poses). :func:`simulate_random_calibration` writes the calibration folder the existing
calibration path (``fringescope calibrate`` / :func:`app.calib.calibrate_folder`) reads; any
scene (:func:`app.devices.sim.scenes.build_scene`) renders with ``RandomRig.rig``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from app.atomic import atomic_write_text
from app.capture.captureset import write_capture_set
from app.core.board import BoardSpec
from app.core.encoding import npy_bytes
from app.devices.sim.offline import auto_exposure_ms, central_fraction, render_capture_set
from app.devices.sim.optics import (
    CameraModel,
    ProjectorModel,
    SimRig,
    plane_through,
    rotation_x,
    rotation_y,
)
from app.devices.sim.scenes import board_poses, board_scene
from app.devices.sim.world import SimulatedWorld

F64 = npt.NDArray[np.float64]

RANDOM_BIT_DEPTHS = (8, 10, 12)
POSES_RANGE = (6, 16)
COVERAGE_RANGE = (1.0 / 3.0, 1.0)  # board reach from the image centre (1 = the image edge)
MIN_SQUARE_PX = 30.0  # smaller squares on a board tilted 30° defeated the detector (20 px did)
DMD_SIZE = (608, 684)  # DLP3000 (width, height)
# heights above the reference plane the projector must light: the far plane scene's -6 mm
# to the board poses' +18 mm and the DOF target's +20 mm
LIT_HEIGHTS_MM = (-8.0, 22.0)


@dataclass(frozen=True)
class RandomRig:
    """One drawn rig and its calibration board set.

    Attributes:
        rig: the twin's rig (camera, projector, reference plane, bit depth).
        seed: the seed it was drawn from.
        board: the board spec (type, inner corners, pitch mm) scaled to ``coverage``.
        coverage: max over poses of the board's reach from the image centre, 0..1 of the half
            width / half height.
        poses: board poses (pose 0 the reference plane).
        triangulation_deg: angle between camera and projector rays at the reference point.
        baseline_mm: projector centre's distance from the camera centre.
    """

    rig: SimRig
    seed: int
    board: BoardSpec
    coverage: float
    poses: int
    triangulation_deg: float
    baseline_mm: float
    pose_seed: int

    def pose_list(self) -> list[tuple[F64, F64]]:
        """(origin, axes) of each board pose; pose 0 is the reference plane."""
        return board_poses(self.rig, self.poses, seed=self.pose_seed)

    def describe(self) -> str:
        """One line: the drawn parameters."""
        cam = self.rig.camera
        w, h = cam.image_size
        k1, k2 = float(cam.dist[0]), float(cam.dist[1])
        return (
            f"{w}x{h}, f = {cam.K[0, 0]:.0f} px, pp offset ({cam.K[0, 2] - (w - 1) / 2:+.0f}, "
            f"{cam.K[1, 2] - (h - 1) / 2:+.0f}) px, k1 {k1:+.3f} k2 {k2:+.3f}, "
            f"{self.rig.bit_depth}-bit, triangulation {self.triangulation_deg:.1f} deg, baseline "
            f"{self.baseline_mm:.1f} mm, reference {self.rig.reference_point_mm[2]:.1f} mm, "
            f"board {self.board.cols}x{self.board.rows} x {self.board.pitch_mm:.3f} mm reaching "
            f"{self.coverage:.2f}, {self.poses} poses"
            + (f", projector k1 {self.rig.projector.radial[0]:+.3f}"
               if self.rig.projector.radial[0] else "")
        )


def _corner_radius(K: F64, size: tuple[int, int]) -> float:
    """Largest distorted normalised radius over the image corners."""
    w, h = size
    dx = max(K[0, 2], w - 1 - K[0, 2]) / K[0, 0]
    dy = max(K[1, 2], h - 1 - K[1, 2]) / K[1, 1]
    return math.hypot(dx, dy)


def distortion_invertible(k1: float, k2: float, r_distorted: float, margin: float = 0.2) -> bool:
    """Whether ``r_d = r (1 + k1 r² + k2 r⁴)`` is strictly increasing (slope ≥ ``margin``) from the
    centre out to the distorted normalised radius ``r_distorted``: else rays fold over."""
    r = np.linspace(0.0, 3.0, 3001)
    rd = r * (1 + k1 * r**2 + k2 * r**4)
    slope = 1 + 3 * k1 * r**2 + 5 * k2 * r**4
    beyond = np.nonzero(rd >= r_distorted)[0]
    if beyond.size == 0:
        return False
    return bool(np.all(slope[: beyond[0] + 1] >= margin))


def _projector_focal(camera: CameraModel, R: F64, centre: F64, reference: SimRig) -> float:
    """Projector focal length (px) whose DMD covers the camera's field at every lit height."""
    w, h = camera.image_size
    u = np.array([0.0, w / 2, w - 1.0, 0.0, w - 1.0, 0.0, w / 2, w - 1.0])
    v = np.array([0.0, 0.0, 0.0, h / 2, h / 2, h - 1.0, h - 1.0, h - 1.0])
    rays = camera.rays(u, v)
    ref = reference.reference
    worst_x = worst_y = 0.0
    for height in LIT_HEIGHTS_MM:
        # a point on ray t·d has height n·(t d) + offset: t = (height − offset) / (n·d)
        t = (height - ref.offset_mm) / (rays @ ref.normal)
        q = (t[:, None] * rays - centre) @ R
        worst_x = max(worst_x, float(np.max(np.abs(q[:, 0] / q[:, 2]))))
        worst_y = max(worst_y, float(np.max(np.abs(q[:, 1] / q[:, 2]))))
    return 0.97 * min((DMD_SIZE[0] / 2) / worst_x, (DMD_SIZE[1] / 2) / worst_y)


def _scaled_board(
    rig: SimRig, cols: int, rows: int, poses: list[tuple[F64, F64]], reach: float
) -> BoardSpec:
    """The board of ``cols`` × ``rows`` inner corners whose pitch (0.001 mm steps) makes its reach
    over ``poses`` just ``reach`` (bisection on the pitch; the reach grows with it)."""
    lo, hi = 0.05, 5.0
    probe = BoardSpec("checkerboard", cols, rows, 1.0)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if central_fraction(rig, mid, probe, poses) > reach:
            hi = mid
        else:
            lo = mid
    return BoardSpec("checkerboard", cols, rows, math.floor(1000.0 * lo) / 1000.0)


def _square_px(rig: SimRig, board: BoardSpec) -> float:
    """A board square's side in pixels at the reference plane (the farthest pose), face on."""
    return board.pitch_mm * float(rig.K[0, 0]) / float(rig.reference_point_mm[2])


def random_rig(seed: int, *, coverage: float | None = None, poses: int | None = None,
               projector_k1_max: float = 0.0) -> RandomRig:
    """Draw a rig from ``seed`` (same seed → same rig).

    Ranges: sensor width 960–1440 px, aspect 0.70–0.82; diagonal field 50–75°; principal point
    within ±3 % of the image centre; k1 ∈ [−0.30, +0.05], k2 ∈ [−0.05, +0.10] (redrawn until
    invertible to the image corners); bit depth 8, 10 or 12; baseline 4–12 mm and triangulation
    angle at the reference point 7–18° (the working distance, 36–54 mm, follows from them); the
    reference plane tilted up to 5° about each axis; board 8–12 × 6–9 inner corners (one fewer
    each way, until 5 columns or 4 rows, while a square would span < 30 px at the reference
    plane) reaching ``coverage`` (default drawn in 1/3–1) of the half field; ``poses`` board
    poses (default drawn in 6–16). ``projector_k1_max`` > 0: the projector lens has a radial
    distortion k1 drawn in ±``projector_k1_max`` (normalised projector coordinates; 2-D, so it
    bends each fringe along its length, which the depth models' projector lacks) from a stream of
    its own, so every other parameter is the rig's without it; 0: a pinhole projector.

    Raises:
        ValueError: ``coverage`` outside 1/3–1, ``poses`` outside 6–16 or ``projector_k1_max``
            outside 0–0.2 (naming the argument).
    """
    if not 0.0 <= projector_k1_max <= 0.2:
        raise ValueError(f"projector_k1_max: must be within 0–0.2, got {projector_k1_max}")
    if coverage is not None and not COVERAGE_RANGE[0] - 1e-9 <= coverage <= COVERAGE_RANGE[1]:
        raise ValueError(f"coverage: must be within 1/3–1, got {coverage}")
    if poses is not None and not POSES_RANGE[0] <= poses <= POSES_RANGE[1]:
        raise ValueError(f"poses: must be within {POSES_RANGE[0]}–{POSES_RANGE[1]}, got {poses}")
    rng = np.random.default_rng(np.random.SeedSequence([0x516, seed]))
    width = 2 * int(rng.integers(480, 721))
    height = 2 * round(width * rng.uniform(0.70, 0.82) / 2)
    fov_deg = rng.uniform(50.0, 75.0)
    f_px = math.hypot(width, height) / 2 / math.tan(math.radians(fov_deg) / 2)
    cx = (width - 1) / 2 + rng.uniform(-0.03, 0.03) * width
    cy = (height - 1) / 2 + rng.uniform(-0.03, 0.03) * height
    K = np.array([[f_px, 0.0, cx], [0.0, f_px, cy], [0.0, 0.0, 1.0]])
    r_corner = _corner_radius(K, (width, height))
    while True:
        k1, k2 = rng.uniform(-0.30, 0.05), rng.uniform(-0.05, 0.10)
        if distortion_invertible(k1, k2, r_corner):
            break
    camera = CameraModel(K, np.array([k1, k2, 0.0, 0.0, 0.0]), (width, height))
    bits = int(rng.choice(RANDOM_BIT_DEPTHS))
    # baseline and triangulation angle drawn together; the working distance follows from them
    # (projector beside the camera, the angle taken at the reference point on the camera axis)
    while True:
        baseline, tri = rng.uniform(4.0, 12.0), rng.uniform(7.0, 18.0)
        distance = baseline / math.tan(math.radians(tri))
        if 36.0 <= distance <= 54.0:
            break
    normal = (
        rotation_x(rng.uniform(-5, 5)) @ rotation_y(rng.uniform(-5, 5)) @ np.array([0.0, 0.0, -1.0])
    )
    point = np.array([0.0, 0.0, distance])
    reference = plane_through(point, normal)
    centre = np.array([baseline, 0.0, 0.0])
    # the projector's axis through the reference point, give or take 2 degrees
    R = rotation_y(-math.degrees(math.atan2(baseline, distance)) + rng.uniform(-2.0, 2.0))
    draft = SimRig(camera, ProjectorModel(np.eye(3), R, centre, DMD_SIZE), reference, point)
    fp = _projector_focal(camera, R, centre, draft)
    Kp = np.array(
        [[fp, 0.0, (DMD_SIZE[0] - 1) / 2], [0.0, fp, (DMD_SIZE[1] - 1) / 2], [0.0, 0.0, 1.0]]
    )
    projector = ProjectorModel(Kp, R, centre, DMD_SIZE)
    if projector_k1_max > 0.0:
        own = np.random.default_rng(np.random.SeedSequence([0x516, seed, 2]))
        projector = replace(projector, radial=(float(own.uniform(-1.0, 1.0)) * projector_k1_max,
                                               0.0))
    focus = distance - rng.uniform(9.0, 13.0)
    rig = SimRig(
        camera,
        projector,
        reference,
        point,
        focus_mm=focus,
        blur_per_inv_mm=0.12 * f_px,
        projector_focus_mm=distance - 10.0,
        name=f"random-{seed}",
        bit_depth=bits,
        partial_boards=False,
    )
    n_poses = int(rng.integers(POSES_RANGE[0], POSES_RANGE[1] + 1)) if poses is None else poses
    reach = float(rng.uniform(*COVERAGE_RANGE)) if coverage is None else float(coverage)
    cols, rows = int(rng.integers(8, 13)), int(rng.integers(6, 10))
    pose_seed = int(rng.integers(2**31))
    pose_list = board_poses(rig, n_poses, seed=pose_seed)
    board = _scaled_board(rig, cols, rows, pose_list, reach)
    # a bench user picks a board the camera resolves: fewer, larger squares on a small board
    while _square_px(rig, board) < MIN_SQUARE_PX and min(cols - 5, rows - 4) > 0:
        cols, rows = cols - 1, rows - 1
        board = _scaled_board(rig, cols, rows, pose_list, reach)
    return RandomRig(
        rig,
        seed,
        board,
        central_fraction(rig, board.pitch_mm, board, pose_list),
        n_poses,
        float(tri),
        float(baseline),
        pose_seed,
    )


def simulate_random_calibration(
    out_dir: str | os.PathLike[str],
    rr: RandomRig,
    *,
    seed: int | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``board.json`` and ``pose_00/`` … of ``rr``'s board at its poses, as
    :func:`app.devices.sim.simulate_calibration_folder` does for a preset (the board's paper a
    1.5-pitch margin around its print; each pose exposed so the white paper stays unsaturated;
    ``capture.json`` records the pose under ``simulated``). Returns the folder.
    """
    spec = rr.board
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paper_half_mm = (max(spec.cols, spec.rows) + 1) * spec.pitch_mm / 2 + 1.5 * spec.pitch_mm
    atomic_write_text(out / "board.json", json.dumps(spec.to_dict(), indent=2) + "\n")
    for k, pose in enumerate(rr.pose_list()):
        world = SimulatedWorld(
            board_scene(rr.rig, spec, pose, paper_half_mm=paper_half_mm),
            rig=rr.rig,
            seed=int(rng.integers(2**31)),
        )
        exposure = round(auto_exposure_ms(world, bits=rr.rig.bit_depth), 2)
        cap, depth, _ = render_capture_set(world.scene, exposure_ms=exposure, world=world)
        cap.extra["simulated"].update(
            {
                "board_origin_mm": pose[0].tolist(),
                "board_axes": pose[1].tolist(),
                "pose": k,
                "random_rig_seed": rr.seed,
            }
        )
        write_capture_set(
            out / f"pose_{k:02d}",
            cap,
            overwrite=overwrite,
            extra_files={"truth_depth.npy": npy_bytes(depth)},
        )
    return out
