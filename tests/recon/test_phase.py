"""N-step wrapped phase, modulation, background and saturation against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.recon.patterns import PatternSchedule, fringe_profile
from app.recon.phase import MODULATION_FLOOR_DN, resolve_levels, wrapped_phase


def _frames(phi, a, b, steps, noise, rng, dtype=np.uint16):
    delta = 2 * math.pi * np.arange(steps) / steps
    img = a + b * np.cos(phi[None] + delta[:, None, None])
    img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, np.iinfo(dtype).max).astype(dtype)


@pytest.mark.parametrize("steps", [3, 4, 5, 8])
def test_phase_noise_matches_theory(steps):
    rng = np.random.default_rng(steps)
    phi = rng.uniform(0, 2 * math.pi, (256, 256))
    a, b, sigma = 20000.0, 2000.0, 20.0
    wp = wrapped_phase(_frames(phi, a, b, steps, sigma, rng), steps)
    err = np.angle(np.exp(1j * (wp.phase[0] - phi)))
    theory = sigma * math.sqrt(2.0 / steps) / b
    rms = float(np.sqrt(np.mean(err**2)))
    assert abs(rms / theory - 1.0) < 0.10, (rms, theory)
    assert abs(float(np.mean(err))) < 3 * theory / 256  # unbiased
    assert np.allclose(wp.modulation[0].mean(), b, rtol=2e-3)
    assert np.allclose(wp.background.mean(), a, rtol=1e-4)
    assert wp.phase.min() >= 0.0 and wp.phase.max() < 2 * math.pi


def test_k1_phase_is_absolute_projector_column():
    sched = PatternSchedule(frequencies=(1,), steps=4, width=608)
    x = np.linspace(0.0, 607.9, 500)
    frames = np.stack([
        np.rint(1000 + 30000 * fringe_profile(sched, 0, n, columns=x)).astype(np.uint16)[None, :]
        for n in range(4)
    ])
    wp = wrapped_phase(frames, 4)
    expected = 2 * math.pi * x / 608
    assert np.max(np.abs(wp.phase[0, 0] - expected)) < 1e-4


def test_saturation_uint8_and_12bit():
    # saturated only when fewer than three unclipped samples remain in a frequency
    f8 = np.full((4, 3, 3), 100, np.uint8)
    f8[2, 1, 1] = 255
    f8[0, 0, 0] = f8[1, 0, 0] = 255
    wp = wrapped_phase(f8, 4)
    assert wp.saturated.tolist() == [[1, 0, 0], [0, 0, 0], [0, 0, 0]]
    assert wp.recovered.tolist() == [[0, 0, 0], [0, 1, 0], [0, 0, 0]]
    f16 = np.full((4, 2, 2), 1000, np.uint16)
    f16[0:2, 0, 0] = 4095
    f16[1, 1, 1] = 4094
    sat = wrapped_phase(f16, 4, max_code=4095).saturated
    assert sat.tolist() == [[True, False], [False, False]]
    assert not wrapped_phase(f16, 4).saturated.any()  # default 65535


@pytest.mark.parametrize("steps", [4, 5, 8])
def test_one_clipped_shift_is_fitted_exactly(steps):
    """Three unclipped samples determine A, B, φ: with one shift clipped the phase is exact."""
    phi = np.linspace(0.0, 2 * math.pi, 720, endpoint=False)[None, :].repeat(2, 0)
    delta = 2 * math.pi * np.arange(steps) / steps
    img = 30000.0 + 20000.0 * np.cos(phi[None] + delta[:, None, None])
    frames = np.rint(img).astype(np.uint16)
    clip_at = int(img.max() - 3000)  # clips the brightest sample of most pixels
    clipped = np.minimum(frames, clip_at)
    wp = wrapped_phase(clipped, steps, max_code=clip_at)
    n_clipped = (clipped >= clip_at).sum(axis=0)
    assert (n_clipped == 1).mean() > 0.3
    assert (wp.recovered == (n_clipped >= 1)).all() and not wp.saturated.any()
    err = np.angle(np.exp(1j * (wp.phase[0] - phi)))
    assert np.abs(err).max() < 2e-4  # rounding to integer codes only
    assert np.allclose(wp.modulation[0], 20000.0, rtol=1e-3)


def test_default_levels():
    # None: the floor of the noise-aware rule (app.recon.validity), in codes at any bit depth
    assert resolve_levels(np.uint8, None, None) == (255, MODULATION_FLOOR_DN)
    assert resolve_levels(np.uint16, 4095, None) == (4095, MODULATION_FLOOR_DN)
    assert resolve_levels(np.uint16, None, 3.0) == (65535, 3.0)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(frames=np.zeros((4, 2, 2), np.float32), steps=4), "frames"),
        (dict(frames=np.zeros((2, 2), np.uint8), steps=4), "frames"),
        (dict(frames=np.zeros((6, 2, 2), np.uint8), steps=4), "frames"),
        (dict(frames=np.zeros((4, 2, 2), np.uint8), steps=2), "steps"),
        (dict(frames=np.zeros((4, 2, 2), np.uint8), steps=4, max_code=300), "max_code"),
        (
            dict(frames=[np.zeros((2, 2), np.uint8)] * 3 + [np.zeros((2, 2), np.uint16)], steps=4),
            "frames",
        ),
    ],
)
def test_bad_input_names_argument(kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        wrapped_phase(**kwargs)


@pytest.mark.parametrize(("steps", "dtype", "max_code"),
                         [(3, np.uint8, 255), (4, np.uint8, 200), (5, np.uint16, 4095),
                          (8, np.uint16, 65535)])
def test_the_compiled_pass_equals_numpy_within_a_few_ulps(steps, dtype, max_code):
    from app.recon.phase import nstep_estimates, nstep_estimates_numpy

    rng = np.random.default_rng(steps)
    background = rng.uniform(0.3, 1.2, (37, 53)) * max_code  # the brightest clip in most shifts
    phi = rng.uniform(0.0, 2 * math.pi, (3, 37, 53))  # three frequencies
    sets = [_frames(p, background, 0.4 * max_code, steps, 0.01 * max_code, rng, np.int64)
            for p in phi]
    frames = np.clip(np.concatenate(sets), 0, max_code).astype(dtype)
    got = nstep_estimates(frames, steps, max_code)
    want = nstep_estimates_numpy(frames, steps, max_code)
    assert got[3].any() and (got[4].any() or steps == 3)  # both flags occur (N = 3: no refit)
    # BLAS sums the N products in another order: a few ulps (one ulp of 2π is 8.9e-16), as
    # angles: a tie (sin sum 0 in integers, common where samples clip) may fall a few ulps
    # below 0 in one pass and wrap to 2π − ulp (seen on an AMD EPYC without AVX-512)
    turn = np.remainder(got[0] - want[0] + math.pi, 2 * math.pi) - math.pi
    np.testing.assert_allclose(turn, 0.0, rtol=0, atol=4e-15)
    for a, b in zip(got[1:3], want[1:3], strict=True):
        np.testing.assert_allclose(a, b, rtol=4e-15, atol=4e-15 * max_code)
    assert (got[0] >= 0).all() and (got[0] < 2 * math.pi).all()
    for a, b in zip(got[3:], want[3:], strict=True):
        assert np.array_equal(a, b)


def test_wrapped_phase_without_numba_is_the_numpy_pass(monkeypatch):
    import app.recon.phase as mod

    rng = np.random.default_rng(8)
    phi = rng.uniform(0.0, 2 * math.pi, (20, 30))
    frames = _frames(phi, 120.0, 140.0, 4, 2.0, rng, np.uint8)  # clipped above 255
    compiled = wrapped_phase(frames, 4)
    monkeypatch.setattr(mod, "_nstep_kernel", None)
    plain = wrapped_phase(frames, 4)
    assert plain.recovered.any()
    np.testing.assert_allclose(plain.phase, compiled.phase, rtol=4e-16, atol=4e-15)
    assert np.array_equal(plain.saturated, compiled.saturated)
    assert np.array_equal(plain.background, compiled.background)
