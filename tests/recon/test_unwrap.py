"""Hierarchical temporal unwrapping: exact orders, the consistency test, the combination."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import compute_phase
from app.recon.unwrap import combine_frequencies, unwrap_chain, unwrap_hierarchical, unwrap_phases

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
    assert combine_frequencies(biased, mod, FREQS, 4)[0, 0] == pytest.approx(
        exact[-1, 0, 0], abs=1e-12
    )
    mod[0] = 1.0
    k = np.array(FREQS, float)
    expected = exact[-1, 0, 0] + 0.1 * 36 * 1 / np.sum(k**2)
    assert combine_frequencies(biased, mod, FREQS, 4)[0, 0] == pytest.approx(expected, abs=1e-12)


HET = (1920 / 48, 1920 / 45, 1920 / 42)  # the CFPE rig's periods of 48, 45 and 42 px


def test_heterodyne_chain_of_three_periods():
    coefs, steps = unwrap_chain(HET, "heterodyne")
    # φ_a − 2φ_b + φ_c spans 0.381 fringe (absolute), φ_c − φ_b 3.05 fringes, then φ_c
    assert coefs.tolist() == [[1, -2, 1], [0, -1, 1], [0, 0, 1]]
    assert np.allclose(
        steps, [1920 / 42 - 2 * 1920 / 45 + 1920 / 48, 1920 / 42 - 1920 / 45, 1920 / 42]
    )
    assert unwrap_chain(FREQS)[0].tolist() == np.eye(4).tolist()


@pytest.mark.parametrize("noise_rad", [0.0, 0.01])  # residual σ ≈ 20 × noise at the first step
def test_heterodyne_exact_orders(noise_rad):
    x = np.linspace(0.0, 1919.0, 40000).reshape(200, 200)
    rng = np.random.default_rng(4)
    wrapped = np.stack(
        [np.mod(TWO_PI * k * x / 1920 + rng.normal(0, noise_rad, x.shape), TWO_PI) for k in HET]
    )
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
    [
        ((40.0, 42.0), "at least 3"),
        ((40.0, 42.0, 44.0), "zero beat"),
        ((10.0, 13.0, 19.0), "not <= 1"),
    ],
)
def test_heterodyne_bad_schedules(freqs, message):
    with pytest.raises(ValueError, match=f"^frequencies: .*{message}"):
        unwrap_chain(freqs, "heterodyne")


# -- the heterodyne order test (a wrong order under motion must not pass) -------------
HET9 = (30, 35, 36)  # the registered heterodyne-9 schedule's fringe counts


def _het9_wrapped(x, w=608.0):
    return np.stack([np.mod(TWO_PI * k * x / w, TWO_PI) for k in HET9])


def test_slip_front_of_30_35_36_is_the_analytic_one():
    from app.recon.unwrap import order_slip_front, order_slip_margin

    # m = ±6: φ_30 unmoved, φ_35 by 2π·6/36; m = ±1: φ_30 by 2π/6, φ_35 by 2π/36 (grid 0.005 rad,
    # rounded down)
    front = order_slip_front(HET9)
    np.testing.assert_allclose(front, [[0.0, TWO_PI / 6], [TWO_PI / 6, TWO_PI / 36]], atol=0.005)
    # never looser
    assert (front <= np.array([[0.0, TWO_PI / 6], [TWO_PI / 6, TWO_PI / 36]]) + 1e-12).all()
    assert order_slip_margin(HET9) == pytest.approx(TWO_PI / 6)
    # motion between the groups can cancel part of a slip: the margin shrinks as the bound grows
    margins = [order_slip_margin(HET9, r) for r in (0.0, 0.1, 0.3, 0.6, 1.2)]
    assert all(b < a for a, b in zip(margins, margins[1:], strict=False))
    assert margins[-1] < 0.1  # unbounded motion: no heterodyne set can tell its orders apart
    with pytest.raises(ValueError, match="^max_motion_rad"):
        order_slip_margin(HET9, -0.1)


@pytest.mark.parametrize("slip", [m for m in range(-35, 36) if m != 0])
def test_a_constructed_order_slip_is_caught(slip):
    from app.recon.unwrap import order_residuals_consistent

    x = np.linspace(3.0, 600.0, 300).reshape(10, 30)
    wrapped = _het9_wrapped(x)
    finest = TWO_PI * 36 * x / 608.0
    var = np.full(wrapped.shape, 0.02**2)  # a well-modulated pixel's phase variance
    assert order_residuals_consistent(wrapped, finest, var, HET9).all()
    assert not order_residuals_consistent(wrapped, finest + TWO_PI * slip, var, HET9).any()


def test_order_test_refuses_pixels_too_noisy_to_show_a_slip():
    from app.recon.unwrap import PHASE_FLOOR_RAD, order_residuals_consistent, order_test_bound

    x = np.full((1, 2), 300.0)
    wrapped = _het9_wrapped(x)
    finest = TWO_PI * 36 * x / 608.0
    z = order_test_bound(3)
    # σ(r_35) just below / above (π/3)/(2z) with σ(r_30) large: only the first can show m = ±6
    lim = (TWO_PI / 6 - 0.005) / (2 * z)
    r35 = np.array([0.97, 1.03]) * lim
    ratio = 35 / 36
    v_fine = 1e-6
    var = np.empty((3, 1, 2))
    var[2] = v_fine
    var[1] = r35**2 - ratio**2 * v_fine - PHASE_FLOOR_RAD**2 * (1 + ratio**2)
    var[0] = 0.05**2
    assert order_residuals_consistent(wrapped, finest, var, HET9).tolist() == [[True, False]]


def test_order_test_false_alarm_rate_on_a_still_noisy_scene(monkeypatch):
    import app.recon.unwrap as unwrap

    # pure Gaussian noise: the stated rate holds
    monkeypatch.setattr(unwrap, "PHASE_FLOOR_RAD", 0.0)
    rng = np.random.default_rng(12)
    x = rng.uniform(20.0, 588.0, (500, 1000))  # away from the ends, where the 1-fringe beat wraps
    sigma = 0.02
    wrapped = np.mod(_het9_wrapped(x) + rng.normal(0.0, sigma, (3, *x.shape)), TWO_PI)
    alpha = 1e-2
    unwrapped, ok = unwrap_phases(
        wrapped,
        HET9,
        "heterodyne",
        phase_var=np.full(wrapped.shape, sigma**2),
        false_alarm_rate=alpha,
    )
    # no order errors at this noise
    assert np.all(np.abs(unwrapped[-1] - TWO_PI * 36 * x / 608.0) < 1.0)
    rate = 1.0 - ok.mean()
    assert 0.6 * alpha < rate < 1.05 * alpha  # Bonferroni over 2 correlated tests: a little below α


def test_motion_between_groups_slips_the_chain_and_the_order_test_catches_it():
    """Each group sees the surface at another instant: the beats move 35× the fine phase's
    change, the chain picks a wrong order at some pixels and still passes its π/2 step test."""
    from app.recon.unwrap import LIVE_MAX_MOTION_RAD

    # the 1-fringe beat wraps at the field ends
    x = np.linspace(20.0, 588.0, 200_000).reshape(400, 500)
    rng = np.random.default_rng(3)
    rho = rng.uniform(-0.3, 0.3, x.shape)  # finest-phase change per group interval, rad
    # groups 30, 35, 36
    wrapped = np.stack([np.mod(TWO_PI * k * x / 608.0 + (k / 36) * rho * (g - 2), TWO_PI)
                        for g, k in enumerate(HET9)])
    truth = TWO_PI * 36 * x / 608.0
    chain, chain_ok = unwrap_phases(wrapped, HET9, "heterodyne")
    slipped = chain_ok & (np.abs(chain[-1] - truth) > math.pi)
    assert slipped.sum() > 100
    var = np.full(wrapped.shape, 0.01**2)
    tested, ok = unwrap_phases(
        wrapped, HET9, "heterodyne", phase_var=var, max_motion_rad=LIVE_MAX_MOTION_RAD
    )
    assert not (ok & (np.abs(tested[-1] - truth) > math.pi)).any()
    assert not ok[slipped].any()
