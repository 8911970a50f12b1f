"""The twin's random rig generator: seeded, within its ranges, physically usable."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.devices.sim.random_rig import (
    COVERAGE_RANGE,
    DMD_SIZE,
    LIT_HEIGHTS_MM,
    POSES_RANGE,
    RANDOM_BIT_DEPTHS,
    distortion_invertible,
    random_rig,
)
from app.devices.sim.scenes import board_points_mm

SEEDS = range(40)


@pytest.fixture(scope="module")
def rigs():  # noqa: ANN201
    return [random_rig(s) for s in SEEDS]


def test_same_seed_same_rig_other_seed_other_rig():
    a, b, c = random_rig(7), random_rig(7), random_rig(8)
    assert np.array_equal(a.rig.K, b.rig.K) and np.array_equal(a.rig.dist, b.rig.dist)
    assert a.board == b.board and a.poses == b.poses
    assert all(
        np.array_equal(p[0], q[0]) and np.array_equal(p[1], q[1])
        for p, q in zip(a.pose_list(), b.pose_list(), strict=True)
    )
    assert not np.array_equal(a.rig.K, c.rig.K)


def test_draws_span_the_ranges(rigs):  # noqa: ANN001
    assert {r.rig.bit_depth for r in rigs} == set(RANDOM_BIT_DEPTHS)
    poses = [r.poses for r in rigs]
    assert POSES_RANGE[0] <= min(poses) < 9 and 13 < max(poses) <= POSES_RANGE[1]
    cover = [r.coverage for r in rigs]
    # the board's reach is set to the drawn coverage (pitch in 0.001 mm steps: a hair under)
    assert COVERAGE_RANGE[0] - 0.02 <= min(cover) < 0.45 and 0.9 < max(cover) <= 1.0
    k1 = [float(r.rig.dist[0]) for r in rigs]
    assert min(k1) < -0.2 and max(k1) > -0.05
    offsets = [abs(r.rig.K[0, 2] - (r.rig.image_size[0] - 1) / 2) for r in rigs]
    assert max(offsets) > 15
    assert len({r.rig.image_size for r in rigs}) == len(rigs)
    tri = [r.triangulation_deg for r in rigs]
    assert 7.0 <= min(tri) < 10.0 and 14.0 < max(tri) <= 18.0


def test_geometry_matches_the_drawn_angle_and_baseline(rigs):  # noqa: ANN001
    for r in rigs:
        p, c = r.rig.reference_point_mm, r.rig.projector.centre
        angle = math.degrees(
            math.acos(float(p @ (p - c)) / (np.linalg.norm(p) * np.linalg.norm(p - c)))
        )
        assert angle == pytest.approx(r.triangulation_deg, abs=1e-6)
        assert float(np.linalg.norm(c)) == pytest.approx(r.baseline_mm)
        assert 36.0 <= p[2] <= 54.0


def test_distortion_round_trips_at_the_image_corners(rigs):  # noqa: ANN001
    """Rays of the corner pixels project back onto them: the lens model does not fold over."""
    for r in rigs:
        cam = r.rig.camera
        w, h = cam.image_size
        u = np.array([0.0, w - 1.0, 0.0, w - 1.0])
        v = np.array([0.0, 0.0, h - 1.0, h - 1.0])
        back = cam.project(cam.rays(u, v) * 40.0)
        assert np.abs(back - np.stack([u, v], -1)).max() < 1e-4, r.describe()
    assert not distortion_invertible(-0.5, 0.0, 1.0)  # folds at r = 0.82 < the corner
    assert distortion_invertible(-0.25, 0.0, 0.68)


def test_projector_lights_the_camera_field_over_the_volume(rigs):  # noqa: ANN001
    for r in rigs:
        cam, proj, ref = r.rig.camera, r.rig.projector, r.rig.reference
        w, h = cam.image_size
        v, u = np.mgrid[0:h:16, 0:w:16].astype(np.float64)
        rays = cam.rays(u, v).reshape(-1, 3)
        for height in LIT_HEIGHTS_MM:
            pts = ((height - ref.offset_mm) / (rays @ ref.normal))[:, None] * rays
            x, y = proj.column(pts), proj.row(pts)
            assert x.min() > -0.5 and x.max() < DMD_SIZE[0] - 0.5, r.describe()
            assert y.min() > -0.5 and y.max() < DMD_SIZE[1] - 0.5, r.describe()


def test_board_stays_in_view_and_resolvable(rigs):  # noqa: ANN001
    for r in rigs:
        cam = r.rig.camera
        w, h = cam.image_size
        for origin, axes in r.pose_list():
            pts = origin + board_points_mm(r.board) @ axes.T
            uv = cam.project(pts)
            assert (
                uv[:, 0].min() > 0
                and uv[:, 0].max() < w - 1
                and uv[:, 1].min() > 0
                and uv[:, 1].max() < h - 1
            )
        # squares of >= 30 px at the reference plane, or as few corners as the generator goes
        assert (
            r.board.pitch_mm * r.rig.K[0, 0] / r.rig.reference_point_mm[2] >= 30.0
            or r.board.cols == 5
            or r.board.rows == 4
        )


@pytest.mark.parametrize(
    ("kw", "name"),
    [({"coverage": 0.2}, "coverage"), ({"poses": 5}, "poses"), ({"poses": 17}, "poses")],
)
def test_bad_arguments_name_themselves(kw, name):  # noqa: ANN001
    with pytest.raises(ValueError, match=name):
        random_rig(1, **kw)


def test_fixed_coverage_and_poses_are_kept():
    r = random_rig(3, coverage=0.5, poses=6)
    assert r.poses == 6 and len(r.pose_list()) == 6
    assert 0.45 <= r.coverage <= 0.5


def test_a_projector_distortion_is_drawn_apart_from_the_rest_of_the_rig():
    """``projector_k1_max``: the projector's radial k1 within ±max, every other part of the rig
    as without it (its own stream); the rig renders it (fringes bend)."""
    plain = random_rig(5)
    bent = random_rig(5, projector_k1_max=0.05)
    assert plain.rig.projector.radial == (0.0, 0.0)
    k1, k2 = bent.rig.projector.radial
    assert 0.0 < abs(k1) <= 0.05 and k2 == 0.0
    np.testing.assert_array_equal(bent.rig.camera.K, plain.rig.camera.K)
    np.testing.assert_array_equal(bent.rig.projector.K, plain.rig.projector.K)
    assert (bent.board, bent.poses, bent.pose_seed) == (plain.board, plain.poses, plain.pose_seed)
    assert "projector k1" in bent.describe() and "projector k1" not in plain.describe()
    p = np.array([[3.0, 2.5, float(plain.rig.reference_point_mm[2])]])
    assert bent.rig.projector.column(p)[0] != pytest.approx(plain.rig.projector.column(p)[0])
    with pytest.raises(ValueError, match="projector_k1_max"):
        random_rig(5, projector_k1_max=0.5)
