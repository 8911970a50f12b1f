"""Ground truth consistent with the rendered fringes; determinism; moving scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.devices.sim import SimulatedWorld, render_capture_set
from app.devices.sim.offline import auto_exposure_ms, frame_times


def _wrapped(frames: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """N-step wrapped phase and modulation of (N, H, W) frames (numpy reference)."""
    d = 2 * np.pi * np.arange(steps) / steps
    s = np.tensordot(np.sin(d), frames, axes=1)
    c = np.tensordot(np.cos(d), frames, axes=1)
    return np.arctan2(-s, c), 2.0 / steps * np.hypot(s, c)


def test_truth_matches_phase_of_rendered_frames(dof_world):
    sched = dof_world.schedule
    exposure = auto_exposure_ms(dof_world, bits=12, target=0.9)
    dof_world.reseed(11)
    cap, depth, points = render_capture_set(
        dof_world.scene, exposure_ms=exposure, bit_depth=12, world=dof_world
    )
    frames = cap.frames.astype(np.float64)
    n = sched.steps
    phases, mods = [], []
    for fi in range(len(sched.frequencies)):
        p, m = _wrapped(frames[fi * n : (fi + 1) * n], n)
        phases.append(p)
        mods.append(m)
    unwrapped = np.mod(phases[0], 2 * np.pi)  # k = 1 is absolute
    for fi in range(1, len(sched.frequencies)):
        ratio = sched.frequencies[fi] / sched.frequencies[fi - 1]
        unwrapped = phases[fi] + 2 * np.pi * np.round(
            (ratio * unwrapped - phases[fi]) / (2 * np.pi)
        )
    xp_true = dof_world.rig.projector.column(points.astype(np.float64))
    phi_true = 2 * math.pi * sched.frequencies[-1] * xp_true / sched.width
    good = np.isfinite(depth) & (mods[-1] > 60) & (cap.frames.max(0) < 4095)
    assert good.mean() > 0.4
    err = unwrapped[good] - phi_true[good]
    # Predicted phase noise of the finest frequency: σ_φ = σ_I·√(2/N)/B (σ_I from the noise model).
    mean_i = frames[-n:].mean(0)[good]
    sigma_phi = dof_world.noise_sigma(mean_i, bits=12) * np.sqrt(2.0 / n) / mods[-1][good]
    zs = err / sigma_phi
    assert abs(np.mean(err)) < 0.003  # no systematic phase error
    assert 0.55 < np.median(np.abs(zs)) < 0.85  # Gaussian: 0.674
    assert np.percentile(np.abs(zs), 99.9) < 5.0  # no unwrapping failures or outliers
    assert cap.extra["simulated"]["truth_time_s"] == pytest.approx(
        float(np.mean(frame_times(16, exposure)[[0, -1]])))


def test_same_seed_same_frames_different_seed_differs(plane_world):
    r = plane_world.renderer

    def frames(seed):
        plane_world.reseed(seed)
        return np.stack(
            [plane_world.render(i, 0.0, exposure_ms=20.0, gain=1.0, bits=8) for i in (0, 17)]
        )

    a, b, c = frames(5), frames(5), frames(6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert r.shape == a.shape[1:]
    w1, w2 = SimulatedWorld("plane", seed=3), SimulatedWorld("plane", seed=3)
    assert w1.rng_state[0] == w2.rng_state[0]


@pytest.mark.slow
def test_moving_scene_truth_and_frames_follow_motion():
    world = SimulatedWorld("intestine_pile", seed=4, distortion=False)
    r = world.renderer
    d0, p0 = r.truth(0.0)
    d2, p2 = r.truth(2.0)  # platform moved 3 mm·sin(π/2) = 3 mm along the platform
    shift = world.scene.offset(2.0) - world.scene.offset(0.0)
    assert np.linalg.norm(shift) == pytest.approx(3.0)
    ok = np.isfinite(d0) & np.isfinite(d2)
    assert ok.mean() > 0.9
    assert np.nanmax(d0) > 5.0  # the pile stands above the platform
    # the truth moved: a sharp edge landscape differs between the two instants
    assert np.mean(np.abs(d2[ok] - d0[ok]) > 0.5) > 0.05
    # the rendered frame at t follows the truth at t better than the truth at 0
    f = r.mean_frame(0, 2.0, exposure_ms=20.0)
    f0 = r.mean_frame(0, 0.0, exposure_ms=20.0)
    assert not np.allclose(f, f0)
