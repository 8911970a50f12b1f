"""An analytic pinhole camera + pinhole projector rig for calibration tests.

Along a camera ray X = t·r the projector column is linear-fractional in t, and the height
above any plane is linear in t, so the phase → height map is exactly Eq. (5) (zero
quadratic terms): a fit must reproduce it to numerical precision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from app.calib.board import BoardSpec
from app.calib.fitting import PoseObservation
from app.core.schedule import PatternSchedule


def rot(ax_deg: float, ay_deg: float, az_deg: float = 0.0) -> np.ndarray:
    rv = np.radians([ax_deg, ay_deg, az_deg])
    rx = cv2.Rodrigues(np.array([rv[0], 0, 0]))[0]
    ry = cv2.Rodrigues(np.array([0, rv[1], 0]))[0]
    rz = cv2.Rodrigues(np.array([0, 0, rv[2]]))[0]
    return rz @ ry @ rx


@dataclass
class Rig:
    width: int = 640
    height: int = 480
    f_px: float = 800.0
    schedule: PatternSchedule = PatternSchedule()
    proj_center_mm: tuple[float, float, float] = (20.0, 0.0, 0.0)
    proj_yaw_deg: float = 12.0
    proj_f_px: float = 600.0

    @property
    def camera_matrix(self) -> np.ndarray:
        return np.array([[self.f_px, 0, (self.width - 1) / 2],
                         [0, self.f_px, (self.height - 1) / 2],
                         [0, 0, 1.0]])

    def rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        k = self.camera_matrix
        return np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)],
                        axis=-1)

    def phase_of_points(self, x: np.ndarray) -> np.ndarray:
        """Finest-frequency phase (rad) lighting camera-frame points x (..., 3) mm."""
        r = rot(0, self.proj_yaw_deg)
        xp = (x - np.array(self.proj_center_mm)) @ r.T
        col = self.proj_f_px * xp[..., 0] / xp[..., 2] + self.schedule.width / 2
        return 2 * math.pi * self.schedule.frequencies[-1] * col / self.schedule.width

    def plane_phase_map(self, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
        """(H, W) phase over the image for an infinite plane through ``point``."""
        vv, uu = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        r = self.rays(uu, vv)
        t = (normal @ point) / (r @ normal)
        return self.phase_of_points(r * t[..., None]).astype(np.float32)

    def observe(self, board: BoardSpec, rmat: np.ndarray, tvec: np.ndarray, name: str = "",
                noise_px: float = 0.0, rng: np.random.Generator | None = None) -> PoseObservation:
        obj = board.object_points()
        rvec = cv2.Rodrigues(rmat)[0]
        img, _ = cv2.projectPoints(obj, rvec, tvec, self.camera_matrix, np.zeros(5))
        img = img.reshape(-1, 2)
        if noise_px:
            img = img + (rng or np.random.default_rng(0)).normal(0, noise_px, img.shape)
        phase = self.plane_phase_map(rmat[:, 2], np.asarray(tvec, np.float64))
        return PoseObservation(img.astype(np.float32), obj, phase, name)


def board_pose(board: BoardSpec, depth_mm: float, ax: float, ay: float, az: float = 0.0,
               shift: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation putting the board centre at (shift, depth) facing the camera."""
    obj = board.object_points()
    centre = obj.mean(axis=0).astype(np.float64)
    r = rot(ax, ay, az)
    t = np.array([shift[0], shift[1], depth_mm]) - r @ centre
    return r, t


STANDARD_POSES = [  # (depth, tilt x, tilt y, spin z, shift) — pose 0 farthest
    (100.0, 4.0, -3.0, 0.0, (0.0, 0.0)),
    (96.0, -12.0, 8.0, 5.0, (3.0, -2.0)),
    (92.0, 10.0, 12.0, -4.0, (-4.0, 2.0)),
    (88.0, -6.0, -14.0, 8.0, (2.0, 3.0)),
    (84.0, 15.0, -5.0, -6.0, (-2.0, -3.0)),
    (80.0, -9.0, 10.0, 3.0, (0.0, 1.0)),
]


def true_height(rig: Rig, ref_r: np.ndarray, ref_t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Height of camera-frame points above the reference board plane, toward the camera."""
    n = ref_r[:, 2]
    if n @ ref_t > 0:
        n = -n
    return x @ n - n @ ref_t


def raycast_scene(rig: Rig, plane: tuple[np.ndarray, np.ndarray], *,
                  sphere: tuple[np.ndarray, float] | None = None,
                  cylinder: tuple[np.ndarray, np.ndarray, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (H, W, 3) of the nearest surface, and a surface id map (0 plane,
    1 sphere, 2 cylinder). ``plane`` = (unit normal, point); ``sphere`` = (centre, radius);
    ``cylinder`` = (axis point, unit axis direction, radius)."""
    vv, uu = np.mgrid[0 : rig.height, 0 : rig.width].astype(np.float64)
    r = rig.rays(uu, vv)
    n, p = plane
    t_best = (n @ p) / (r @ n)
    sid = np.zeros(t_best.shape, np.uint8)
    if sphere is not None:
        c, rad = sphere
        b = r @ c
        rr = np.sum(r * r, axis=-1)
        disc = b * b - rr * (c @ c - rad * rad)
        t = np.where(disc >= 0, (b - np.sqrt(np.clip(disc, 0, None))) / rr, np.inf)
        hit = t < t_best
        t_best, sid = np.where(hit, t, t_best), np.where(hit, 1, sid).astype(np.uint8)
    if cylinder is not None:
        p0, a, rad = cylinder
        d = r - (r @ a)[..., None] * a
        m = -p0 - (-p0 @ a) * a
        qa = np.sum(d * d, axis=-1)
        qb = 2 * (d @ m)
        qc = m @ m - rad * rad
        disc = qb * qb - 4 * qa * qc
        t = np.where(disc >= 0, (-qb - np.sqrt(np.clip(disc, 0, None))) / (2 * qa), np.inf)
        hit = t < t_best
        t_best, sid = np.where(hit, t, t_best), np.where(hit, 2, sid).astype(np.uint8)
    return r * t_best[..., None], sid


def fringe_frames(rig: Rig, points: np.ndarray, albedo: np.ndarray, *, noise_dn: float = 0.5,
                  seed: int = 0) -> np.ndarray:
    """(16, H, W) uint8 fringe frames of camera-frame points with the given albedo (0..1)."""
    return fringe_stack(rig, rig.phase_of_points(points), albedo, noise_dn=noise_dn, seed=seed)


def fringe_stack(rig: Rig, phi: np.ndarray, albedo: np.ndarray, *, noise_dn: float = 0.5,
                 seed: int = 0) -> np.ndarray:
    """(16, H, W) uint8 frames: albedo × (110 + 100 cos(k/k_max · φ + δ)) + Gaussian noise."""
    sched = rig.schedule
    rng = np.random.default_rng(seed)
    frames = []
    for k in sched.frequencies:
        for d in sched.shifts_rad:
            img = albedo * (110.0 + 100.0 * np.cos(phi * k / sched.frequencies[-1] + d))
            noisy = np.rint(img + rng.normal(0, noise_dn, img.shape))
            frames.append(np.clip(noisy, 0, 255).astype(np.uint8))
    return np.stack(frames)


BOARD = BoardSpec("checkerboard", 9, 7, 3.0)  # the fit tests' board

SCALE = 40.0  # raster px per mm for rendering


def render_board(board: BoardSpec, rmat: np.ndarray, tvec: np.ndarray, rig: Rig) -> np.ndarray:
    """Image of the board through the rig's camera (white margin, blurred edges)."""
    obj = board.object_points()
    lo = obj[:, :2].min(axis=0) - 2 * board.pitch_mm
    hi = obj[:, :2].max(axis=0) + 2 * board.pitch_mm
    w, h = ((hi - lo) * SCALE).astype(int)
    yy, xx = np.mgrid[0:h, 0:w]
    x = lo[0] + (xx + 0.5) / SCALE
    y = lo[1] + (yy + 0.5) / SCALE
    if board.type == "checkerboard":
        inside = ((x > -board.pitch_mm) & (x < board.cols * board.pitch_mm)
                  & (y > -board.pitch_mm) & (y < board.rows * board.pitch_mm))
        dark = ((np.floor(x / board.pitch_mm) + np.floor(y / board.pitch_mm)) % 2 == 0) & inside
    else:
        dark = np.zeros((h, w), bool)
        for px, py, _ in obj:
            dark |= (x - px) ** 2 + (y - py) ** 2 < (0.35 * board.pitch_mm) ** 2
    raster = np.where(dark, 30, 220).astype(np.uint8)
    # raster pixel → board mm → image
    s = np.array([[1 / SCALE, 0, lo[0] + 0.5 / SCALE],
                  [0, 1 / SCALE, lo[1] + 0.5 / SCALE],
                  [0, 0, 1]])
    # Supersample 4x (pixel centres at (4i + 1.5)) then box-average, so edges are area-weighted.
    up = np.array([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]])
    hmat = up @ rig.camera_matrix @ np.column_stack([rmat[:, 0], rmat[:, 1], tvec]) @ s
    big = cv2.warpPerspective(raster, hmat, (4 * rig.width, 4 * rig.height), flags=cv2.INTER_LINEAR,
                              borderValue=200)
    img = cv2.resize(big, (rig.width, rig.height), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(img, (0, 0), 0.8)
