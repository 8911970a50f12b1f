"""Hierarchical temporal unwrapping: exact orders, the consistency test, the combination."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.recon import compute_phase
from app.recon.unwrap import combine_frequencies, unwrap_chain, unwrap_hierarchical, unwrap_phases
from tests.recon.analytic_rig import Rig, bump_surface

FREQS = (1, 4, 12, 36)
TWO_PI = 2 * math.pi


def _wrapped(x, w=608.0):
    return np.stack([np.mod(TWO_PI * k * x / w, TWO_PI) for k in FREQS])


def test_exact_data_has_zero_order_errors():
    x = np.linspace(0.5, 607.5, 20000).reshape(100, 200)
    unwrapped, ok = unwrap_hierarchical(_wrapped(x), FREQS)
    assert ok.all()
    for i, k in enumerate(FREQS):
        assert np.max(np.abs(unwrapped[i] - TWO_PI * k * x / 608)) < 1e-9


def test_rendered_rig_unwraps_without_order_errors():
    rig = Rig()
    h = bump_surface(rig)
    frames = rig.render(h, background=30000, amplitude=25000, dtype=np.uint16)
    res = compute_phase(frames, rig.schedule)
    assert (res.reason == 0).all()
    err = np.abs(res.phase - rig.finest_phase(h))
    assert err.max() < 0.01  # an order error would be 2π


@pytest.mark.parametrize(
    ("index", "bump_rad", "consistent"),
    [
        (3, 0.3, True), (3, 1.0, True), (3, 2.0, False), (3, -2.5, False),
        (1, 0.3, True),
        (1, 1.0, False),  # an error on k = 4 reaches the 4 → 12 step tripled (3.0 rad)
    ],
)
def test_consistency_threshold(index, bump_rad, consistent):
    x = np.full((1, 1), 300.0)
    w = _wrapped(x)
    w[index] = np.mod(w[index] + bump_rad, TWO_PI)
    _, ok = unwrap_hierarchical(w, FREQS, consistency_rad=math.pi / 2)
    assert bool(ok[0, 0]) is consistent


def test_consistency_rad_validated():
    w = _wrapped(np.ones((1, 1)))
    for bad in (0.0, -1.0, 3.5, float("nan")):
        with pytest.raises(ValueError, match="^consistency_rad"):
            unwrap_hierarchical(w, FREQS, consistency_rad=bad)
    with pytest.raises(ValueError, match="^frequencies"):
        unwrap_hierarchical(w, (2, 4, 12, 36))


def test_combined_estimate_is_exact_on_exact_data_and_less_noisy():
    x = np.linspace(5.0, 600.0, 40000).reshape(200, 200)
    exact, _ = unwrap_hierarchical(_wrapped(x), FREQS)
    mod = np.full(exact.shape, 50.0)
    assert np.max(np.abs(combine_frequencies(exact, mod, FREQS, 4) - exact[-1])) < 1e-9
    # equal noise σ on every wrapped map: the finest-only error is σ, the combined
    # σ·k_max/√Σk² (inverse-variance weights ∝ N·B²·k²).
    rng = np.random.default_rng(7)
    sigma = 0.05
    noisy, ok = unwrap_hierarchical(_wrapped(x) + rng.normal(0, sigma, exact.shape), FREQS)
    assert ok.all()
    finest = np.std(noisy[-1] - exact[-1])
    combined = np.std(combine_frequencies(noisy, mod, FREQS, 4) - exact[-1])
    k = np.array(FREQS, float)
    assert finest == pytest.approx(sigma, rel=0.02)
    assert combined == pytest.approx(sigma * k[-1] / np.sqrt(np.sum(k**2)), rel=0.02)


def test_combined_weights_follow_modulation():
    x = np.full((1, 1), 200.0)
    exact, _ = unwrap_hierarchical(_wrapped(x), FREQS)
    biased = exact.copy()
    biased[0] += 0.1  # error on k = 1 only
    mod = np.ones_like(exact)
    mod[0] = 0.0  # ... which has no modulation, hence no weight
    assert combine_frequencies(biased, mod, FREQS, 4)[0, 0] == pytest.approx(exact[-1, 0, 0], abs=1e-12)
    mod[0] = 1.0
    k = np.array(FREQS, float)
    expected = exact[-1, 0, 0] + 0.1 * 36 * 1 / np.sum(k**2)
    assert combine_frequencies(biased, mod, FREQS, 4)[0, 0] == pytest.approx(expected, abs=1e-12)


HET = (1920 / 48, 1920 / 45, 1920 / 42)  # the CFPE rig's periods of 48, 45 and 42 px


def test_heterodyne_chain_of_three_periods():
    coefs, steps = unwrap_chain(HET, "heterodyne")
    # φ_a − 2φ_b + φ_c spans 0.381 fringe (absolute), φ_c − φ_b 3.05 fringes, then φ_c
    assert coefs.tolist() == [[1, -2, 1], [0, -1, 1], [0, 0, 1]]
    assert np.allclose(steps, [1920 / 42 - 2 * 1920 / 45 + 1920 / 48, 1920 / 42 - 1920 / 45, 1920 / 42])
    assert unwrap_chain(FREQS)[0].tolist() == np.eye(4).tolist()


@pytest.mark.parametrize("noise_rad", [0.0, 0.01])  # residual σ ≈ 20 × noise at the first step
def test_heterodyne_exact_orders(noise_rad):
    x = np.linspace(0.0, 1919.0, 40000).reshape(200, 200)
    rng = np.random.default_rng(4)
    wrapped = np.stack([np.mod(TWO_PI * k * x / 1920 + rng.normal(0, noise_rad, x.shape), TWO_PI) for k in HET])
    unwrapped, ok = unwrap_phases(wrapped, HET, "heterodyne")
    assert ok.all()
    for i, k in enumerate(HET):
        assert np.max(np.abs(unwrapped[i] - TWO_PI * k * x / 1920)) < 6 * noise_rad + 1e-9


def test_heterodyne_flags_inconsistent_pixels():
    x = np.full((1, 1), 700.0)
    wrapped = np.stack([np.mod(TWO_PI * k * x / 1920, TWO_PI) for k in HET])
    wrapped[1] = np.mod(wrapped[1] + 1.0, TWO_PI)  # 1 rad on φ_b reaches the first beat doubled
    assert not unwrap_phases(wrapped, HET, "heterodyne")[1].all()


@pytest.mark.parametrize(
    ("freqs", "message"),
    [((40.0, 42.0), "at least 3"), ((40.0, 42.0, 44.0), "zero beat"), ((10.0, 13.0, 19.0), "not <= 1")],
)
def test_heterodyne_bad_schedules(freqs, message):
    with pytest.raises(ValueError, match=f"^frequencies: .*{message}"):
        unwrap_chain(freqs, "heterodyne")
