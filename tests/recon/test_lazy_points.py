"""Points on demand: the fast path's 3-D points are made from depth on the first read, once,
with the values the kernel used to write; every other output is unchanged."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor
from app.recon.fusion import fuse_exposures
from app.recon.motion import MotionTest
from app.recon.points import LazyPoints, PointRays, calibration_ray_tables, ray_quotients
from app.recon.sensor import SensorNoise

NOISE = SensorNoise(gain_dn_per_e=0.02, read_noise_dn=0.5)


@pytest.fixture(scope="module")
def rig():
    return Rig()


@pytest.fixture(scope="module")
def frames(rig):
    return rig.render(bump_surface(rig), background=110, amplitude=90, noise=1.0,
                      rng=np.random.default_rng(5))


def _float32_points(cal, depth):
    """(h − offset)·q in float32, computed here independently of the result."""
    q = ray_quotients(calibration_ray_tables(cal))
    t = depth.astype(np.float32) - np.float32(cal.plane_offset_mm)
    return (t[..., None] * q).astype(np.float32)


def test_fast_points_are_made_once_on_demand_from_depth(rig, frames):
    cal = rig.calibration()
    rec = Reconstructor(cal)
    res = rec.run(frames, noise=NOISE)
    assert LazyPoints.given(res) is None and res.point_rays is not None  # not made by run
    pts = res.points
    assert pts.shape == (rig.height, rig.width, 3) and pts.dtype == np.float32
    assert res.points is pts  # kept: made at most once
    assert np.array_equal(pts, _float32_points(cal, res.depth), equal_nan=True)
    assert np.isnan(pts[~res.valid]).all() and np.isfinite(pts[res.valid]).all()
    ref = rec.run(frames, noise=NOISE, fast=False)  # the numpy path gives them eagerly
    assert LazyPoints.given(ref) is not None and ref.point_rays is None
    ok = res.valid & ref.valid
    assert ok.mean() > 0.9
    assert np.max(np.abs(res.points[ok] - ref.points[ok])) < 1e-3  # mm
    assert np.array_equal(res.valid, ref.valid)


def test_threads_reading_points_at_once_get_the_same_array(rig, frames):
    res = Reconstructor(rig.calibration()).run(frames, noise=NOISE)
    got: list[np.ndarray] = []
    start = threading.Barrier(4)

    def read() -> None:
        start.wait()
        got.append(res.points)

    threads = [threading.Thread(target=read) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert len(got) == 4 and all(g is got[0] for g in got)


def test_pooled_results_never_show_stale_points(rig, frames):
    """A recycled result makes its points from its own depth; points a caller keeps stay as
    they were (the pool does not reuse a result whose points are referenced)."""
    cal = rig.calibration()
    rec = Reconstructor(cal)
    other = rig.render(bump_surface(rig) * 0.5, background=110, amplitude=90, noise=1.0,
                       rng=np.random.default_rng(6))
    kept = rec.run(frames, noise=NOISE).points  # the result itself is dropped
    kept_copy = kept.copy()
    for _ in range(3):  # results dropped at once are recycled
        res = rec.run(other, noise=NOISE)
        assert LazyPoints.given(res) is None
        assert np.array_equal(res.points, _float32_points(cal, res.depth), equal_nan=True)
        del res
    assert np.array_equal(kept, kept_copy, equal_nan=True)


def test_motion_invalidated_pixels_have_no_points(rig, frames):
    moved = frames.copy()
    moved[4:8, 30:60, 40:90] = np.clip(moved[4:8, 30:60, 40:90].astype(int) + 60, 0, 255)
    rec = Reconstructor(rig.calibration())
    res = rec.run(moved, noise=NOISE, motion=MotionTest(grow_px=1))
    assert res.moved_pixels > 0
    motion = res.motion
    assert motion is not None and not res.valid[motion].any()
    assert np.isnan(res.points[motion]).all()
    assert np.array_equal(np.isnan(res.points).any(axis=-1), ~res.valid)
    ref = rec.run(moved, noise=NOISE, motion=MotionTest(grow_px=1), fast=False)
    assert np.array_equal(res.valid, ref.valid)
    assert np.max(np.abs(res.points[res.valid] - ref.points[res.valid])) < 1e-3


def test_fused_bracket_points_are_the_members_points(rig):
    h = bump_surface(rig)
    rec = Reconstructor(rig.calibration())
    members = []
    for scale in (1.0, 2.2):  # the longer exposure clips the bright fringes
        f = rig.render(h, background=110 * scale, amplitude=90 * scale, noise=1.0,
                       rng=np.random.default_rng(int(10 * scale)))
        members.append(rec.run(np.clip(f, 0, 255).astype(np.uint8), noise=NOISE))
    fused = fuse_exposures(members, [10.0, 22.0])
    res = fused.result
    assert LazyPoints.given(res) is None and res.point_rays is members[0].point_rays
    pick = np.clip(fused.member, 0, None)
    expect = np.where((pick == 0)[..., None], members[0].points, members[1].points)
    assert np.array_equal(res.points[res.valid], expect[res.valid])
    assert np.isnan(res.points[~res.valid]).all()


def test_point_rays_check_their_heights():
    rays = PointRays(np.ones((2, 3, 3), np.float32), np.float32(1.0))
    assert np.array_equal(rays.points(np.full((2, 3), 3.0, np.float32)),
                          np.full((2, 3, 3), 2.0, np.float32))
    with pytest.raises(ValueError, match="height_mm"):
        rays.points(np.zeros((2, 3), np.float64))
    with pytest.raises(ValueError, match="height_mm"):
        rays.points(np.zeros((3, 2), np.float32))
