"""The interactive calibration: a board spec, captured poses, solve, activate.

Each pose is one whole fringe set of the board; its texture is searched for the board
right away so the user sees whether it will count. Pose 0 (the first detected pose)
is the reference plane.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from app.calib.board import Detection, detect_board, texture_to_u8
from app.calib.coverage import (
    CoverageMap,
    PoseAdvice,
    board_views,
    coverage_map,
    model_sigma,
    suggest_pose,
)
from app.calib.fitting import CalibrationReport, ObservedSet, calibrate_observed, observe_set
from app.capture.captureset import CaptureSet
from app.core.board import BoardSpec
from app.core.encoding import png_bytes
from app.core.errors import NotFound
from app.core.schedule import PatternSchedule
from app.devices.sim.optics import SimRig
from app.recon import compute_phase

log = logging.getLogger("fringescope.service")


@dataclass
class Pose:
    """One captured view of the board: what the wizard shows and what the solve fits.

    The fringe set itself is not kept: ``observed`` holds what the fit needs of it (phase and
    points, ~11 MB), where the frames are tens of MB a pose.

    Attributes:
        observed: the calibration's view of the set (:func:`~app.calib.fitting.observe_set`,
            its own phase threshold and board search), None where no board was found.
        detection: the board found in the pose's texture (shown to the user).
        preview_png: the texture with the detected points drawn, PNG bytes.
        exposure_ms: the set's exposure, ms; led: its LED.
        frame_shape: (F, H, W) of the set's frames; schedule: their pattern schedule.
        phase: (H, W) float32 finest unwrapped phase, rad, when found (the coverage's σ_model).
    """

    observed: ObservedSet | None
    detection: Detection
    preview_png: bytes
    exposure_ms: float
    led: str
    frame_shape: tuple[int, int, int]
    schedule: PatternSchedule
    phase: npt.NDArray[np.float32] | None = None
    created: str = field(default_factory=lambda: datetime.now(UTC).isoformat(timespec="seconds"))

    @property
    def found(self) -> bool:
        return bool(self.detection.found)

    def summary(self, index: int) -> dict[str, Any]:
        return {
            "index": index,
            "found": self.found,
            "corners": int(len(self.detection.image_points)),
            "created": self.created,
            "exposure_ms": self.exposure_ms,
            "led": self.led,
            "preview_url": f"/api/calibration/session/poses/{index}/preview.png",
        }


def preview_png(texture_u8: np.ndarray, board: BoardSpec, detection: Detection) -> bytes:
    """The texture with the detected board points drawn (OpenCV's coloured corner chain)."""
    img = cv2.cvtColor(texture_u8, cv2.COLOR_GRAY2BGR)
    if detection.found:
        pts = detection.image_points.reshape(-1, 1, 2).astype(np.float32)
        cv2.drawChessboardCorners(img, board.pattern_size, pts, True)
    return png_bytes(img)


_NOT_FOUND = Detection(False, np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32))


def finest_texture(frames: np.ndarray, schedule: PatternSchedule) -> np.ndarray:
    """A + B of the finest frequency's N frames: the texture the board is searched in.

    Args:
        frames: (F, H, W) frames in capture-set order, any integer dtype.
        schedule: their pattern schedule.

    Returns:
        (H, W) float32, codes. The same image as the phase computation's texture, from one
        group (about 50 ms instead of seconds for the whole set on a loaded machine).
    """
    if frames.ndim != 3 or frames.shape[0] != schedule.n_frames:
        raise ValueError(f"frames: expected ({schedule.n_frames}, H, W), got {frames.shape}")
    n = schedule.steps
    g = int(np.argmax(schedule.frequencies))
    group = frames[g * n:(g + 1) * n].astype(np.float32)
    delta = 2.0 * np.pi * np.arange(n) / n
    re = np.tensordot(np.cos(delta).astype(np.float32), group, axes=1)
    im = np.tensordot(np.sin(delta).astype(np.float32), group, axes=1)
    texture: npt.NDArray[np.float32] = (group.mean(axis=0)
                                        + (2.0 / n) * np.hypot(re, im)).astype(np.float32)
    return texture


def board_in_view(texture_u8: np.ndarray, board: BoardSpec) -> bool:
    """Whether a checkerboard may be in view: False only when two quick detectors find none.

    The full detection's exhaustive fallback takes seconds on a view without a board (4.5 s
    on a 1384 x 1032 twin frame); the classic detector with its fast check (0.2 s) and the
    sector-based one at half resolution (0.3 s, for low-contrast boards) answer "no board"
    within a second. Circle grids are searched directly (their detector is fast).

    Args:
        texture_u8: (H, W) uint8 texture of the pose.
        board: the board spec.
    """
    if board.type != "checkerboard":
        return True
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, _ = cv2.findChessboardCorners(texture_u8, board.pattern_size, flags=flags)
    if found:
        return True
    half = cv2.resize(texture_u8, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    found, _ = cv2.findChessboardCornersSB(half, board.pattern_size,
                                           flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    return bool(found)


class CalibrationSession:
    """Poses of one board; ``solve()`` fits a calibration from the detected ones."""

    def __init__(self, board: BoardSpec) -> None:
        self.board = board
        self.poses: list[Pose] = []
        self.report: CalibrationReport | None = None  # once solved
        self.created = datetime.now(UTC).isoformat(timespec="seconds")
        self.lock = threading.Lock()
        self._coverage: tuple[CoverageMap, PoseAdvice] | None = None
        self._version = 0  # poses added or deleted

    def add(self, capture: CaptureSet) -> tuple[int, Pose]:
        """Detect the board in ``capture`` and keep it as the next pose."""
        tex = texture_to_u8(finest_texture(capture.frames, capture.schedule))
        if board_in_view(tex, self.board):  # the full phase and detection only then: seconds
            res = compute_phase(capture.frames, capture.schedule, max_code=capture.max_code)
            tex = texture_to_u8(res.texture)
            det = detect_board(tex, self.board)
            phase = res.phase if det.found else None
        else:
            det, phase = _NOT_FOUND, None
        # the solve's phase (its own modulation threshold) now, so the frames need not be kept
        observed = observe_set(self.board, capture) if det.found else None
        shape = capture.frames.shape
        pose = Pose(observed, det, preview_png(tex, self.board, det), capture.exposure_ms,
                    capture.led, (int(shape[0]), int(shape[1]), int(shape[2])),
                    capture.schedule, phase)
        with self.lock:
            self.poses.append(pose)
            self.report = None
            self._coverage = None
            self._version += 1
            index = len(self.poses) - 1
        self.coverage()  # the map and the next pose, while the user looks at this one
        return index, pose

    def coverage(self) -> tuple[CoverageMap, PoseAdvice]:
        """The image x height cells the found poses cover, σ_model per cell and the next pose
        (:mod:`app.calib.coverage`; recomputed after a pose is added or deleted)."""
        with self.lock:
            if self._coverage is not None:
                return self._coverage
            found = [p for p in self.poses if p.found]
            shape = self.poses[0].frame_shape if self.poses else (0, 1, 1)
            version = self._version
        size = (int(shape[2]), int(shape[1]))  # before any pose: unknown, a 1 x 1 image
        if not found:
            cov = coverage_map([], size)
            result = cov, suggest_pose(cov, [])
        else:
            img = [p.detection.image_points for p in found]
            sched = found[0].schedule
            phases = [p.phase for p in found if p.phase is not None]
            try:
                views = board_views(img, [p.detection.object_points for p in found], size)
                fringes = int(round(float(sched.frequencies[-1])))
                sigma = None if len(phases) != len(found) else model_sigma(
                    views, phases, img, fringes=fringes, projector_width_px=sched.axis_length)
                cov = coverage_map(views.poses, size, sigma=sigma)
                result = cov, suggest_pose(cov, views.poses)
            except (ValueError, cv2.error, np.linalg.LinAlgError) as exc:  # guidance only: say why
                log.warning("calibration coverage: %s", exc)
                cov = coverage_map([], size)
                result = cov, suggest_pose(cov, [])
        with self.lock:
            if self._version == version:  # no pose added or deleted meanwhile
                self._coverage = result
        return result

    def coverage_dict(self) -> dict[str, Any]:
        """:meth:`coverage` as the REST answers carry it: the map and the suggestion."""
        cov, advice = self.coverage()
        status = cov.status_line() if cov.poses else "no pose with the board yet"
        return {**cov.to_dict(), "status": status,
                "suggestion": advice_dict(advice)}

    def pose(self, index: int) -> Pose:
        with self.lock:
            if not 0 <= index < len(self.poses):
                raise NotFound(f"pose {index}: no such pose (have {len(self.poses)})")
            return self.poses[index]

    def delete(self, index: int) -> None:
        with self.lock:
            if not 0 <= index < len(self.poses):
                raise NotFound(f"pose {index}: no such pose (have {len(self.poses)})")
            del self.poses[index]
            self.report = None
            self._coverage = None
            self._version += 1

    def summaries(self) -> list[dict[str, Any]]:
        with self.lock:
            return [p.summary(i) for i, p in enumerate(self.poses)]

    def solve(self, *, robust: bool = False) -> CalibrationReport:
        """Fit from the detected poses (the first one is the reference plane)."""
        with self.lock:
            used = [(i, p) for i, p in enumerate(self.poses) if p.found]
        if not used:
            raise ValueError("poses: no pose with the board detected")
        names = [f"pose_{i:02d}" for i, _ in used]
        observed: list[ObservedSet] = []
        for _, p in used:
            assert p.observed is not None, "observe_set runs for every pose whose board is found"
            observed.append(p.observed)
        report = calibrate_observed(self.board, observed, robust=robust, names=names)
        with self.lock:
            self.report = report
        return report

    def describe(self) -> dict[str, Any]:
        """What the wizard needs to show the session again (after a page reload, say)."""
        return {
            "board": self.board.to_dict(),
            "created": self.created,
            "poses": self.summaries(),
            "solved": self.report is not None,
            "coverage": self.coverage_dict(),
        }


def advice_dict(advice: PoseAdvice) -> dict[str, Any]:
    """A :class:`PoseAdvice` as JSON."""
    return {"region": advice.region, "u_px": round(advice.u_px, 1), "v_px": round(advice.v_px, 1),
            "height_mm": round(advice.height_mm, 2), "tilt_vertical_deg": advice.tilt_vertical_deg,
            "tilt_horizontal_deg": advice.tilt_horizontal_deg, "text": advice.text}


def twin_board_pose(rig: SimRig, board: BoardSpec, advice: PoseAdvice, *, margin_px: float = 40.0
                    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(origin, axes) of the twin's board for ``advice``: its centre on the ray of the advised
    pixel at the advised height, tilted as advised (signs of
    :class:`~app.calib.coverage.PoseGeometry`);
    moved toward the image centre until every corner is ``margin_px`` inside the image.

    Args:
        rig: the twin's rig (its camera and reference plane).
        board: the session's board (its corners must stay in view).
        advice: the suggestion.
    """
    from app.devices.sim.scenes import board_points_mm
    from app.devices.sim.scenes.base import frame_from_normal

    ref = rig.reference
    n0 = np.asarray(ref.normal, np.float64)
    x_ax = np.array([1.0, 0.0, 0.0]) - n0[0] * n0
    x_ax /= np.linalg.norm(x_ax)
    y_ax = np.cross(n0, x_ax)
    y_ax = y_ax if y_ax[1] >= 0 else -y_ax
    tv, th = np.radians(advice.tilt_vertical_deg), np.radians(advice.tilt_horizontal_deg)
    normal = n0 - np.tan(tv) * x_ax - np.tan(th) * y_ax
    normal /= np.linalg.norm(normal)
    w, h = rig.image_size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    target = np.array([advice.u_px, advice.v_px])
    corners = board_points_mm(board)
    pose = frame_from_normal(np.zeros(3), normal)
    for step in np.linspace(1.0, 0.0, 21):
        uv = centre + step * (target - centre)
        ray = rig.camera.rays(np.array([uv[0]]), np.array([uv[1]])).reshape(3)
        origin = ray * (advice.height_mm - ref.offset_mm) / float(n0 @ ray)
        pose = frame_from_normal(origin, normal)
        px = rig.camera.project(origin + corners @ pose[1].T)
        if (px.min(axis=0) >= margin_px).all() and (px[:, 0] <= w - 1 - margin_px).all() \
                and (px[:, 1] <= h - 1 - margin_px).all():
            break
    return pose
