"""The fused numba kernel: its atan2, its agreement with the numpy oracle, its disk cache."""

from __future__ import annotations

import math
import re

import numpy as np
import numpy.typing as npt
import pytest
from numba import njit

from app.devices.sim.analytic_rig import Rig, bump_surface, reason_scene
from app.recon import Reconstructor, fast
from tests.helpers.analytic_models import geometric_of, rig_calibration


@njit(cache=False)
def atan2_array(y: npt.NDArray[np.float32], x: npt.NDArray[np.float32],
                coarse: bool = False) -> npt.NDArray[np.float32]:  # pragma: no cover - compiled
    """The kernel's :func:`fast.atan2_0_2pi` (or :func:`fast.atan2_coarse`) over 1-D float32."""
    out = np.empty(y.shape[0], np.float32)
    for i in range(y.shape[0]):
        out[i] = fast.atan2_coarse(y[i], x[i]) if coarse else fast.atan2_0_2pi(y[i], x[i])
    return out


def test_polynomial_atan2_error():
    rng = np.random.default_rng(0)
    y = rng.normal(size=400_000).astype(np.float32)
    x = rng.normal(size=400_000).astype(np.float32)
    # axes, diagonals, signed zeros and tiny values
    edge = np.array([0, 1, -1, 1e-30, -1e-30, 3, -3, 0.0, -0.0], np.float32)
    ey, ex = (a.ravel() for a in np.meshgrid(edge, edge))
    y, x = np.concatenate([y, ey]), np.concatenate([x, ex])
    got = atan2_array(y, x).astype(np.float64)
    ref = np.mod(np.arctan2(y.astype(np.float64), x.astype(np.float64)), 2 * math.pi)
    diff = np.abs(np.angle(np.exp(1j * (got - ref))))
    # undefined direction: the kernel returns 0 (numpy: 0 or ±π by sign bits)
    zero = (x == 0) & (y == 0)
    assert (got[zero] == 0).all()
    assert diff[~zero].max() < 1e-6  # ≪ 1e-4 rad
    assert got.min() >= 0.0 and got.max() < 2 * math.pi


@pytest.mark.parametrize("combine", [False, True])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_fast_agrees_with_numpy(dtype, combine):
    rig = Rig()
    frames, _, _ = reason_scene(rig, dtype=dtype, noise=2.0, seed=11)
    rec = Reconstructor(rig.calibration(), max_code=None if dtype == np.uint8 else 4095,
                        with_phase=True, combine_frequencies=combine)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    assert np.array_equal(a.reason, b.reason)
    assert np.array_equal(a.valid, b.valid)
    ok = a.valid
    assert ok.mean() > 0.7
    assert np.max(np.abs(a.depth[ok] - b.depth[ok])) < 1e-3
    assert np.max(np.abs(a.points[ok] - b.points[ok])) < 1e-3
    assert (np.isnan(b.depth[~ok]).all() and np.isnan(b.points[~ok]).all()
            and np.isnan(b.phase[~ok]).all())
    assert np.max(np.abs(a.phase[ok] - b.phase[ok])) < 1e-3
    assert np.allclose(a.modulation, b.modulation, rtol=1e-5, atol=1e-3)
    assert np.allclose(a.texture, b.texture, rtol=1e-5, atol=1e-3)
    for r in (a, b):
        assert (r.depth.dtype == r.points.dtype == r.modulation.dtype == r.texture.dtype
                == np.float32)
        assert r.reason.dtype == np.uint8 and r.valid.dtype == np.bool_


def test_kernel_is_cached_on_disk():
    from numba.core.caching import NullCache

    assert not isinstance(fast.fused_kernel._cache, NullCache)
    fast.warmup(np.uint8)
    fast.warmup(np.uint16)
    dtypes = {str(sig[0].dtype) for sig in fast.fused_kernel.signatures}
    assert {"uint8", "uint16"} <= dtypes


def test_the_height_stage_pixel_loop_is_vectorised(monkeypatch):
    # LLVM vectorises the height stage's pixel loop only while the pixel function is inlined and
    # the loop needs at most 128 run-time alias checks (fast._height_row's docstring); scalar, it
    # took 3-4x the CPU of the rest of the kernel. A fresh (uncached) compile of the row function
    # for a geometric model with a radial projector lens, the most arrays any model reads, must
    # hold vector float divisions and square roots.
    rig = Rig()
    frames, _, _ = reason_scene(rig, dtype=np.uint8, noise=2.0, seed=5)
    kernel = fast.fused_kernel
    args: list[fast.HeightArgs] = []

    def spy(frames_: object, ph: object, m: fast.HeightArgs, out: object) -> None:
        args.append(m)
        kernel(frames_, ph, m, out)

    monkeypatch.setattr(fast, "fused_kernel", spy)
    Reconstructor(rig_calibration(rig, geometric_of(rig, k1=-0.05))).run(frames)
    m = args[-1]  # the first may be the warm-up's
    assert m.use_rays and m.use_cross
    row = njit(fastmath=fast.FASTMATH, error_model="numpy")(fast._height_row.py_func)
    width = frames.shape[2]

    def f32() -> npt.NDArray[np.float32]:
        return np.ones(width, np.float32)

    row(0, f32(), f32(), f32(), f32(), np.zeros(width, np.uint8), m, f32(), f32(),
        np.zeros(width, np.uint8), np.zeros(width, np.bool_), f32(), f32(), np.float32(0.5),
        np.zeros((5, width), np.float32))
    ir = "".join(row.inspect_llvm().values())
    assert re.search(r"fdiv [^\n]*<\d+ x float>", ir), "the height stage's loop is scalar"
    assert re.search(r"@llvm\.sqrt\.v\d+f32", ir), "the height stage's loop is scalar"


def test_numpy_fallback_when_numba_missing(monkeypatch):
    import app.recon.reconstructor as mod

    rig = Rig()
    frames, _, _ = reason_scene(rig)
    expected = Reconstructor(rig.calibration(), fast=False).run(frames)
    monkeypatch.setattr(mod, "_fast", None)
    rec = Reconstructor(rig.calibration(), fast=True)
    assert rec.fast is False
    got = rec.run(frames)
    assert np.array_equal(got.reason, expected.reason)
    assert np.array_equal(got.depth, expected.depth, equal_nan=True)


def test_concurrent_runs_from_two_threads():
    # numba's workqueue layer aborts the process on concurrent parallel launches; the
    # engine serialises its kernel, so the service's threads may call run() freely
    import threading

    rig = Rig()
    frames, _, _ = reason_scene(rig, dtype=np.uint8, noise=2.0, seed=3)
    rec = Reconstructor(rig.calibration())
    expected = rec.run(frames, fast=True)
    mismatches: list[int] = []

    def worker() -> None:
        for _ in range(20):
            res = rec.run(frames, fast=True)
            if not np.array_equal(res.reason, expected.reason):
                mismatches.append(1)

    threads = [threading.Thread(target=worker) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads)
    assert mismatches == []


def test_coarse_atan2_error():
    rng = np.random.default_rng(1)
    y = rng.normal(size=400_000).astype(np.float32)
    x = rng.normal(size=400_000).astype(np.float32)
    got = atan2_array(y, x, True).astype(np.float64)
    ref = np.mod(np.arctan2(y.astype(np.float64), x.astype(np.float64)), 2 * math.pi)
    diff = np.abs(np.angle(np.exp(1j * (got - ref))))
    assert diff.max() < 2e-5  # orders need ≪ π / ratio
    assert got.min() >= 0.0 and got.max() < 2 * math.pi


@pytest.mark.parametrize("steps, frequencies",
                         [(3, (1, 6, 36)), (5, (1, 4, 12, 36)), (4, (1, 8, 40))])
def test_fast_agrees_with_numpy_on_other_schedules(steps, frequencies):
    # the general (row-by-row) path of the kernel; the paper's 4 × 4 has its own
    from app.recon import PatternSchedule

    rig = Rig(schedule=PatternSchedule(frequencies=frequencies, steps=steps))
    frames, _, _ = reason_scene(rig, noise=1.0, seed=3)
    rec = Reconstructor(rig.calibration(), with_phase=True)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    assert np.array_equal(a.reason, b.reason)
    ok = a.valid
    assert ok.mean() > 0.7
    assert np.max(np.abs(a.depth[ok] - b.depth[ok])) < 1e-3
    assert np.max(np.abs(a.points[ok] - b.points[ok])) < 1e-3
    assert np.max(np.abs(a.phase[ok] - b.phase[ok])) < 1e-3
    assert np.allclose(a.texture, b.texture, rtol=1e-5, atol=1e-3)


def test_phase_is_optional():
    rig = Rig()
    frames, _, _ = reason_scene(rig)
    for fast_path in (True, False):
        assert Reconstructor(rig.calibration(), fast=fast_path).run(frames).phase is None


@pytest.mark.parametrize("combine", [False, True])
@pytest.mark.parametrize("steps", [3, 4, 6])
def test_fast_agrees_with_numpy_heterodyne(steps, combine):
    from app.recon import PatternSchedule

    sched = PatternSchedule(frequencies=(608 / 48, 608 / 45, 608 / 42), steps=steps,
                            unwrap="heterodyne")
    rig = Rig(schedule=sched)
    frames = rig.render(bump_surface(rig), background=110, amplitude=90, noise=0.5,
                        rng=np.random.default_rng(5))
    rec = Reconstructor(rig.calibration(), with_phase=True, combine_frequencies=combine)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    assert a.valid.mean() > 0.99
    assert np.array_equal(a.reason, b.reason)
    ok = a.valid
    assert np.max(np.abs(a.phase[ok] - b.phase[ok])) < 1e-3
    assert np.max(np.abs(a.depth[ok] - b.depth[ok])) < 1e-3
    assert np.max(np.abs(a.phase[ok] - rig.finest_phase(bump_surface(rig))[ok])) < 0.1


@pytest.mark.parametrize(("steps", "frequencies", "combine"),
                         [(4, (1, 4, 12, 36), False), (4, (1, 4, 12, 36), True),
                          (5, (1, 6, 36), False)])
def test_fast_agrees_with_numpy_on_clipped_samples(steps, frequencies, combine):
    """One clipped shift per frequency in a band of pixels: both paths refit it from the rest."""
    from app.recon import PatternSchedule

    rig = Rig(schedule=PatternSchedule(frequencies=frequencies, steps=steps))
    h = bump_surface(rig)
    clean = rig.render(h, background=130, amplitude=110, noise=0.5, rng=np.random.default_rng(2))
    frames = clean.copy()
    frames[::steps, 30:90] = 255  # shift 0 of every frequency clipped in rows 30..89
    rec = Reconstructor(rig.calibration(), with_phase=True, combine_frequencies=combine)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    ref = rec.run(clean, fast=False)
    assert np.array_equal(a.reason, b.reason)
    band = np.zeros(a.valid.shape, bool)
    band[30:90] = True
    assert a.recovered == b.recovered == int(
        (band & ref.valid).sum() + (band & ~ref.valid & a.valid).sum())
    ok = a.valid
    assert (a.valid[band] == ref.valid[band]).mean() > 0.99
    assert np.max(np.abs(a.phase[ok] - b.phase[ok])) < 1e-3
    assert np.max(np.abs(a.depth[ok] - b.depth[ok])) < 1e-3
    both = ok & ref.valid & band
    assert abs(float(np.mean(a.depth[both] - ref.depth[both]))) < 0.01  # no bias from the refit


@pytest.mark.parametrize(("schedule", "combine"), [
    (dict(frequencies=(1, 4, 12, 36), steps=4), False),
    (dict(frequencies=(1, 4, 12, 36), steps=4), True),
    (dict(frequencies=(608 / 48, 608 / 45, 608 / 42), steps=4, unwrap="heterodyne"), False),
    (dict(frequencies=(608 / 48, 608 / 45, 608 / 42), steps=5, unwrap="heterodyne"), True),
])
def test_fast_sigma_agrees_with_numpy_on_refitted_and_heterodyne_pixels(schedule, combine):
    """The merged kernel: σ of the height stage follows the phase stage's refit and heterodyne
    chain."""
    from app.recon import PatternSchedule

    rig = Rig(schedule=PatternSchedule(**schedule))
    steps = rig.schedule.steps
    frames = rig.render(bump_surface(rig), background=130, amplitude=110, noise=0.5,
                        rng=np.random.default_rng(3))
    frames[::steps, 30:90] = 255  # one clipped shift per frequency: refitted
    rec = Reconstructor(rig.calibration(), combine_frequencies=combine)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    assert np.array_equal(a.reason, b.reason) and a.recovered == b.recovered > 0
    ok = a.valid
    assert ok[30:90].mean() > 0.99
    np.testing.assert_allclose(b.sigma[ok], a.sigma[ok], rtol=1e-4)
    assert np.isnan(b.sigma[~ok]).all()


@pytest.mark.parametrize("motion_rad", [0.0, 0.3])
def test_fast_agrees_with_numpy_on_the_heterodyne_order_test(motion_rad):
    """heterodyne-9 (the registry's [30, 35, 36] × 3) with the modulation falling across the image:
    the dim columns fail the order test (too noisy for a wrong order to show) in both paths
    alike."""
    from app.core.reasons import Reason
    from app.core.schedule import schedule_by_name

    rig = Rig(schedule=schedule_by_name("heterodyne-9"))
    h = bump_surface(rig)
    amplitude = np.linspace(90.0, 3.0, rig.width)[None, :] * np.ones((rig.height, 1))
    frames = rig.render(h, background=100, amplitude=amplitude, noise=1.0,
                        rng=np.random.default_rng(8))
    # an explicit modulation threshold: the noise-aware one (app.recon.validity) would reject the
    # dim columns first (LOW_MODULATION outranks), and this test is about the order test
    rec = Reconstructor(rig.calibration(), with_phase=True, order_max_motion_rad=motion_rad,
                        min_modulation=1.0)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    assert np.array_equal(a.reason, b.reason)
    inconsistent = a.reason == Reason.UNWRAP_INCONSISTENT
    dim = slice(rig.width // 2, None)
    assert inconsistent[:, dim].mean() > 0.1
    assert inconsistent[:, : rig.width // 4].mean() < 0.01
    ok = a.valid
    assert ok.mean() > 0.4
    assert np.max(np.abs(a.phase[ok] - b.phase[ok])) < 1e-3
    # no wrong order among the valid
    assert np.max(np.abs(a.phase[ok] - rig.finest_phase(h)[ok])) < 0.3


def test_heterodyne_depth_under_motion_between_groups_is_valid_only_where_right():
    """Each frequency group rendered at another height (the surface moves between groups): the
    chain alone slips at some pixels; with the order test every valid depth is the finest
    group's."""
    from app.core.schedule import schedule_by_name
    from app.recon.phase import wrapped_phase
    from app.recon.unwrap import LIVE_MAX_MOTION_RAD, unwrap_phases

    sched = schedule_by_name("heterodyne-9")
    rig = Rig(schedule=sched)
    h = bump_surface(rig)
    rng = np.random.default_rng(4)
    # the height change per group interval, mm: 0 at the left edge, ±2 mm at the right corners
    step_mm = (np.linspace(0.0, 2.0, rig.width)[None, :]
               * np.linspace(-1.0, 1.0, rig.height)[:, None])
    frames = np.empty((9, rig.height, rig.width), np.uint8)
    for g in range(3):  # groups 30, 35, 36; 36 (the map's instant) last
        f = rig.render(h + (g - 2) * step_mm, background=100, amplitude=80, noise=0.5, rng=rng)
        frames[3 * g:3 * g + 3] = f[3 * g:3 * g + 3]
    truth = rig.finest_phase(h)
    wp = wrapped_phase(frames, 3)
    chain, chain_ok = unwrap_phases(wp.phase, sched.frequencies, "heterodyne")
    assert (chain_ok & (np.abs(chain[-1] - truth) > math.pi)).sum() > 100  # the chain alone slips
    rec = Reconstructor(rig.calibration(), with_phase=True,
                        order_max_motion_rad=LIVE_MAX_MOTION_RAD)
    for fast_path in (False, True):
        res = rec.run(frames, fast=fast_path)
        ok = res.valid
        assert ok.mean() > 0.05
        assert np.max(np.abs(res.phase[ok] - truth[ok])) < 0.5
