"""The camera noise model estimated from the N-step fit residual of one fringe set."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon.noise import MAX_PIXELS, estimate_sensor_noise, fit_sensor_noise
from app.recon.patterns import PatternSchedule


@pytest.mark.parametrize("steps", [4, 6, 12])
def test_estimate_recovers_shot_and_read_noise(steps):
    rig = Rig(width=320, height=240, focal_px=400.0, schedule=PatternSchedule(steps=steps))
    clean = rig.render(
        bump_surface(rig), background=600.0, amplitude=300.0, dtype=np.uint16
    ).astype(np.float64)
    # albedo varies across the image so intensities span a wide range
    albedo = np.linspace(0.2, 1.0, rig.width)[None, None, :]
    mean = clean * albedo
    gain, read = 0.5, 4.0
    rng = np.random.default_rng(3)
    frames = np.rint(mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)).astype(
        np.uint16
    )
    est = estimate_sensor_noise(frames, rig.schedule)
    assert est.gain_dn_per_e == pytest.approx(gain, rel=0.05)
    assert est.read_noise_dn == pytest.approx(math.sqrt(read**2 + 1 / 12), rel=0.15)


@pytest.mark.slow
def test_a_moving_scene_keeps_a_read_noise_the_motion_test_takes():
    """The twin's anastomosis at 20 ms moves during the set: the fit's read noise came out 0 and
    the live motion test refused it (no depth map); it is at least the rounding noise, and
    the gain the sensor's within the breathing's share."""
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.radiometry import SensorModel
    from app.recon.motion import motion_mask
    from app.recon.noise import QUANTISATION_NOISE_DN

    cap, _, _ = render_capture_set("anastomosis", exposure_ms=20, seed=1)
    est = estimate_sensor_noise(cap.frames, cap.schedule, max_code=cap.max_code)
    assert est.read_noise_dn >= QUANTISATION_NOISE_DN
    # the forceps are not noise: the fit read 0.58 DN/e⁻ from 5,118 pixels, 36× the sensor's
    # 0.016 (now 0.020: the breathing tissue adds to the residual)
    assert est.gain_dn_per_e < 2.0 * SensorModel().dn_per_electron(8, 1.0)
    moved = motion_mask(cap.frames, len(cap.schedule.frequencies), noise=est, max_code=cap.max_code)
    assert moved.shape == cap.frames.shape[1:]


def _moving_tool_frames(steps: int, tool_share: float, gain: float, read: float,
                        seed: int = 3) -> tuple[np.ndarray, PatternSchedule]:
    """A set whose top-right corner is a bright textured tool (about 5× the scene's median
    level) moving during the set: each frame sees its texture shifted, the shift fading to
    nothing over 12 px of its rim, so its residuals run in a continuum from noise to far
    beyond it; noise ``read² + gain·I`` everywhere."""
    rig = Rig(width=320, height=240, focal_px=400.0, schedule=PatternSchedule(steps=steps))
    mean = rig.render(bump_surface(rig), background=600.0, amplitude=300.0,
                      dtype=np.uint16).astype(np.float64)
    mean *= np.linspace(0.2, 1.0, rig.width)[None, None, :]
    f, h, w = mean.shape
    rows, cols = int(h * math.sqrt(tool_share)), int(w * math.sqrt(tool_share))
    yy, xx = np.mgrid[0:rows, 0:cols]
    rim = np.minimum.reduce([yy + 1, rows - yy, xx + 1, cols - xx]).astype(np.float64)
    speed = np.clip(rim / 12.0, 0.0, 1.0)
    for i in range(f):
        mean[i, :rows, w - cols:] = 1500.0 + 900.0 * np.cos(2 * np.pi * (xx + 9.0 * i * speed)
                                                            / 23.0)
    rng = np.random.default_rng(seed)
    noisy = mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)
    return np.rint(noisy).astype(np.uint16), rig.schedule


@pytest.mark.parametrize("steps", [4, 8])
@pytest.mark.parametrize("tool_share", [0.05, 0.2])
def test_a_large_moving_tool_is_not_noise(steps, tool_share):
    """A moving tool over 5–20 % of the view, brighter than all the scene: its pixels, even
    those whose residual stays small, carry neither the noise line nor the set's harmonics
    (before: gain 0.57 DN/e⁻ for 0.5 and read noise at the rounding floor for 4 DN)."""
    gain, read = 0.5, 4.0
    frames, schedule = _moving_tool_frames(steps, tool_share, gain, read)
    fit = fit_sensor_noise(frames, schedule)
    assert fit.noise.gain_dn_per_e == pytest.approx(gain, rel=0.05)
    assert fit.noise.read_noise_dn == pytest.approx(math.sqrt(read**2 + 1 / 12), rel=0.15)
    assert fit.pixels < (1.0 - 0.9 * tool_share) * frames.shape[1] * frames.shape[2]


@pytest.mark.slow
def test_forceps_over_the_dim_anastomosis_leave_the_sensor_noise():
    """The twin anastomosis at half the LED current (the bright suture's set in
    ``bench_accuracy.py``): the forceps cover ~15 % of the view and hold nearly all its
    brightest pixels. The fit read 0.90 DN/e⁻ from the forceps' 1,500 pixels, σ 7× the
    sensor's, and refused every pixel of the suture as uncertain. The tissue breathes
    during the set, which is not noise either (both anastomosis sets read 1.4–1.6× the
    sensor's gain), so the bound is 2×."""
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.radiometry import SensorModel

    cap, _, _ = render_capture_set("anastomosis_bright", exposure_ms=30.0, current=0.5, seed=7,
                                   t0_s=1.0 - 7.5 * 0.030 - 0.015)  # a breathing extremum
    fit = fit_sensor_noise(cap.frames, cap.schedule, max_code=cap.max_code)
    sensor_gain = SensorModel().dn_per_electron(8, 1.0)
    assert sensor_gain <= fit.noise.gain_dn_per_e < 2.0 * sensor_gain
    h, w = cap.frames.shape[1:]
    step = max(1, math.isqrt(h * w // MAX_PIXELS))
    assert fit.pixels > 0.7 * cap.frames[0, ::step, ::step].size  # the tissue, not the forceps


def test_estimate_needs_more_than_three_steps():
    rig = Rig(schedule=PatternSchedule(steps=3))
    frames = rig.render(bump_surface(rig))
    with pytest.raises(ValueError, match="N > 3"):
        estimate_sensor_noise(frames, rig.schedule)


def test_projector_gamma_harmonics_are_not_noise():
    """A gamma-distorted fringe (10–90 % of the projector range, γ = 2.2): with N = 12 the estimate
    still finds the sensor's noise."""
    rig = Rig(width=320, height=240, focal_px=400.0, schedule=PatternSchedule(steps=12))
    lin = (
        rig.render(bump_surface(rig), background=30000.0, amplitude=24000.0, dtype=np.uint16)
        / 60000.0
    )
    mean = 2000.0 * lin**2.2 * np.linspace(0.3, 1.0, rig.width)[None, None, :]
    gain, read = 0.5, 4.0
    rng = np.random.default_rng(4)
    noisy = mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)
    frames = np.clip(np.rint(noisy), 0, 65535).astype(np.uint16)
    est = estimate_sensor_noise(frames, rig.schedule)
    assert est.gain_dn_per_e == pytest.approx(gain, rel=0.1)
    # the four-step subset: its one residual per frequency is the second harmonic plus noise;
    # the harmonic, common to the set, is fitted out and the same noise found
    four = PatternSchedule(steps=4)
    sub = frames.reshape(4, 12, *frames.shape[1:])[:, ::3].reshape(16, *frames.shape[1:])
    fit4 = fit_sensor_noise(sub, four)
    truth = read**2 + 1 / 12 + gain * 1000.0
    assert abs(fit4.noise.variance_dn2(1000.0) - truth) < 3 * fit4.variance_se_dn2(1000.0)


#: the 2nd harmonic's share of B in :func:`_brightness_harmonic_set`: at the median level,
#: and its coefficients of t = A/1600 − 1 and of t²
SHARE_AT_MEDIAN, SHARE_SLOPE, SHARE_CURVE = 0.10, -0.08, 0.5


def _brightness_harmonic_set(rng: np.random.Generator) -> tuple[np.ndarray, float, float]:
    """A 4-step, 3-frequency 12-bit set whose 2nd harmonic, as a fraction of B, changes with
    the pixel's level A (the real CFPE projector's kind, not a power law): r_2 = 0.10 −
    0.08·t + 0.5·t², t = A/1600 − 1. A varies across the image (1200 … 2000 DN) and the
    amplitude B down it (300 … 1100 DN), so the harmonic is not a function of B. Shot + read
    noise: (frames (12, 240, 320) uint16, read² DN², gain DN/e⁻)."""
    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    level = 1200.0 + 800.0 * x / w  # above B: no sample clipped at 0
    amp = 300.0 + 800.0 * y / h
    t = level / 1600.0 - 1.0
    ratio = SHARE_AT_MEDIAN + SHARE_SLOPE * t + SHARE_CURVE * t**2
    read, gain = 4.0, 0.5
    frames = []
    for k in (1, 4, 12):
        theta = 2.0 * np.pi * k * (x + 0.3 * y) / w
        for n in range(4):
            phase = theta + 2.0 * np.pi * n / 4
            mean = level + amp * (np.cos(phase) + ratio * np.cos(2.0 * phase))
            noisy = mean + rng.normal(size=mean.shape) * np.sqrt(read**2 + gain * mean)
            frames.append(np.clip(np.rint(noisy), 0, 4095).astype(np.uint16))
    return np.stack(frames), read**2 + 1 / 12, gain


def test_harmonics_that_change_with_brightness_are_not_noise():
    """The set-wide harmonics are quadratic in the pixel's level: a 2nd harmonic whose share
    of B changes with A (0.10 … 0.15 over the set; its departure from the median share
    reaches 55 DN, the noise is 30 DN) is fitted out and the sensor's noise found within 3
    standard errors; the fit reads the harmonic at the set's median level and its
    coefficients of A/Ã − 1 and (A/Ã − 1)²."""
    frames, read2, gain = _brightness_harmonic_set(np.random.default_rng(6))
    fit = fit_sensor_noise(frames, PatternSchedule(frequencies=(1, 4, 12), steps=4),
                           max_code=4095)
    assert abs(fit.gain_dn_per_e - gain) < 3 * fit.gain_se
    for level in (1300.0, 1600.0, 1900.0):
        truth = read2 + gain * level
        assert abs(fit.noise.variance_dn2(level) - truth) < 3 * fit.variance_se_dn2(level)
    # the centre is the median level of the fitted pixels (A is uniform over 1200 … 2000 DN)
    centre = fit.brightness_centre
    assert centre == pytest.approx(1600.0, rel=0.02)
    # the truth in the fit's own t = A/Ã − 1: t_truth = s·(1 + t) − 1, s = Ã/1600
    s = centre / 1600.0
    at_median = SHARE_AT_MEDIAN + SHARE_SLOPE * (s - 1) + SHARE_CURVE * (s - 1) ** 2
    slope = (SHARE_SLOPE + 2 * SHARE_CURVE * (s - 1)) * s
    curve = SHARE_CURVE * s**2
    # within 3 standard errors (their spread over seeds 6–9: 3·10⁻⁴, 1.3·10⁻³, 7·10⁻³)
    assert fit.harmonics[:, 0, 0] == pytest.approx(at_median, abs=1e-3)
    assert fit.harmonic_slopes[:, 0, 0, 0] == pytest.approx(slope, abs=4e-3)
    assert fit.harmonic_slopes[:, 0, 1, 0] == pytest.approx(curve, abs=0.03)


# -- the projector's gamma on the twin ---------------------------------------------------------

GAMMA = 1.5  # the twin's DMD response exponent, left uncorrected
FREQS = (1.0, 4.0, 12.0, 36.0)


@pytest.fixture(scope="module")
def twin_set() -> Iterator[Callable[[str, float], tuple]]:
    """:func:`_twin_set` rendered once per (rig, gamma) for the module: the four tests below
    asked for 3 distinct sets 9 times (a full-size render each). The sets are read only (the
    noise fit and the reconstruction read the frames); dropped when the module ends."""
    rendered: dict[tuple[str, float], tuple] = {}

    def get(rig_name: str, gamma: float) -> tuple:
        if (rig_name, gamma) not in rendered:
            rendered[(rig_name, gamma)] = _twin_set(rig_name, gamma)
        return rendered[(rig_name, gamma)]

    yield get
    rendered.clear()


def _twin_set(rig_name: str, gamma: float, seed: int = 2):
    """intestine_flap at 15 ms on rig ``rig_name`` (no camera distortion) with projector
    ``gamma``: (capture set, truth depth, the sensor's σ_I² model as (read² DN², gain))."""
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.optics import rig_by_name
    from app.devices.sim.world import SimulatedWorld

    rig = rig_by_name(rig_name, distortion=False)
    world = SimulatedWorld("intestine_flap", seed=seed, projector_gamma=gamma, rig=rig)
    cs, truth, _ = render_capture_set("intestine_flap", exposure_ms=15.0, world=world)
    sensor = world.renderer.sensor
    g = sensor.dn_per_electron(cs.bit_depth, 1.0)
    return cs, truth, ((g * sensor.read_noise_e) ** 2 + 1 / 12, g)


def test_numba_kernels_equal_the_numpy_versions(monkeypatch, twin_set):
    """The one-pass statistics and the harmonic fit in numba give the numpy versions' fit."""
    from app.recon import noise

    cs, _, _ = twin_set("endoscope", GAMMA)
    fast = noise.fit_sensor_noise(cs.frames, cs.schedule, max_code=cs.max_code)
    monkeypatch.setattr(noise, "_nb", None)
    slow = noise.fit_sensor_noise(cs.frames, cs.schedule, max_code=cs.max_code)
    assert fast.pixels == slow.pixels > 10_000
    # fastmath sums in another order: equal to rounding
    assert fast.gain_dn_per_e == pytest.approx(slow.gain_dn_per_e, rel=1e-6)
    assert fast.read_var_dn2 == pytest.approx(slow.read_var_dn2, rel=1e-6)


def test_a_gamma_15_projector_leaves_the_sensor_noise_on_a_12_bit_twin(twin_set):
    """The old fit read the gamma's second harmonic as noise (113.9 DN/e⁻ against the sensor's
    0.256): the fit is now the sensor's within 3 standard errors, at the set's median
    intensity and at its 10th and 90th percentiles."""
    cs, _, (read2, gain) = twin_set("endoscope", GAMMA)
    fit = fit_sensor_noise(cs.frames, cs.schedule, max_code=cs.max_code)
    lit = cs.frames.mean(axis=0)
    for level in np.percentile(lit[lit > 50], [10, 50, 90]):
        truth = read2 + gain * level
        assert abs(fit.noise.variance_dn2(level) - truth) < 3 * fit.variance_se_dn2(level)
    assert abs(fit.gain_dn_per_e - gain) < 3 * fit.gain_se
    # the standard error is small against what σ needs: σ_I within 1 % (σ ∝ σ_I)
    mid = float(np.median(lit[lit > 50]))
    assert fit.variance_se_dn2(mid) / fit.noise.variance_dn2(mid) < 0.02


def test_a_gamma_15_projector_gives_the_gamma_10_noise_on_the_8_bit_twin(twin_set):
    """8-bit: the same noise as the linear projector's set within 3 combined standard errors,
    and within 4 % of the sensor's model at the set's usual levels (sub-DN noise rounded to
    codes and the darkest pixels cut at 0 make the realised noise of an 8-bit set 1–3 % below
    it there, and 8 % at 10 DN, with either gamma: the fit's read² is 0.10 DN² for 0.12)."""
    cs1, _, (read2, gain) = twin_set("default", 1.0)
    cs15, _, _ = twin_set("default", GAMMA)
    f1 = fit_sensor_noise(cs1.frames, cs1.schedule, max_code=cs1.max_code)
    f15 = fit_sensor_noise(cs15.frames, cs15.schedule, max_code=cs15.max_code)
    assert f15.gain_dn_per_e < 0.02  # was 6.1 DN/e⁻
    for level in (10.0, 25.0, 60.0):
        se = math.hypot(f1.variance_se_dn2(level), f15.variance_se_dn2(level))
        assert abs(f15.noise.variance_dn2(level) - f1.noise.variance_dn2(level)) < 3 * se
    for level in (25.0, 60.0):
        assert f15.noise.variance_dn2(level) == pytest.approx(read2 + gain * level, rel=0.04)


@pytest.mark.slow
def test_gamma_15_depth_with_and_without_a_phase_error_table(twin_set):
    """Reconstructor(cal).run on a gamma 1.5 twin fits the sensor's noise, with or without a
    table from ``fringescope gamma``: as many lit, unsaturated pixels valid as at gamma 1.0,
    none off by > 0.5 mm. With the learned table RMS(e/σ) ≈ 1; without one the set's own 2nd
    harmonic gives the table (:mod:`app.recon.gamma_model`) and RMS(e/σ) ≈ 1 too (it was
    1.25 before), while gamma 1.0 keeps its RMS(e/σ) and valid share. With no table at all
    (the noise given, so none is inferred) the uncorrected phase error (≈ 0.01 rad) is a depth
    error beyond the noise: RMS(e/σ) ≈ 1.25, still no gross error. (The twin's projector IS
    a power law: this checks the plumbing, not the inference; tests/recon/test_gamma_model.py
    checks that on a real projector.)"""
    from app.core.schedule import PatternSchedule
    from app.devices.sim.ideal import ideal_calibration
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.optics import rig_by_name
    from app.devices.sim.world import SimulatedWorld
    from app.recon import Reconstructor
    from app.recon.gamma import PhaseErrorLUT

    rig = rig_by_name("default", distortion=False)
    cal = ideal_calibration(rig)
    twelve = PatternSchedule(frequencies=FREQS, steps=12)
    world = SimulatedWorld("dof_target", schedule=twelve, seed=1, projector_gamma=GAMMA, rig=rig)
    ref, _, _ = render_capture_set("dof_target", exposure_ms=10.0, world=world)
    lut = PhaseErrorLUT.learn(ref.frames, 12, 4, frequencies=FREQS, max_code=ref.max_code)

    def run(gamma: float, table: PhaseErrorLUT | None,
            infer: bool = True) -> tuple[float, float, int, str]:
        cs, truth, _ = twin_set("default", gamma)
        rec = Reconstructor(cal, phase_error=table)
        res = rec.run(cs.frames, max_code=cs.max_code)
        assert res.noise_source == "set" and res.noise is not None
        assert res.noise.gain_dn_per_e < 0.02
        if not infer:  # the same noise given: no table is inferred from the set
            res = rec.run(cs.frames, max_code=cs.max_code, noise=res.noise)
        lit = np.isfinite(truth) & (res.reason != 2)
        ok = res.valid & np.isfinite(truth)
        err = res.depth[ok] - truth[ok]
        rms_z = float(np.sqrt(np.mean((err / res.sigma[ok]) ** 2)))
        return ok.sum() / lit.sum(), rms_z, int((np.abs(err) > 0.5).sum()), res.phase_error_source

    share1, z1, gross1, src1 = run(1.0, None)
    share1_plain, z1_plain, _, _ = run(1.0, None, infer=False)
    share_set, z_set, gross_set, src_set = run(GAMMA, None)
    share_plain, z_plain, gross_plain, src_plain = run(GAMMA, None, infer=False)
    share_table, z_table, gross_table, src_table = run(GAMMA, lut)
    # gamma 1.0: the set's table is below MIN_TABLE_RMS_RAD, none is applied
    assert (src1, src_set, src_plain, src_table) == ("none", "set", "none", "learned")
    assert share1 > 0.95
    assert share1 == share1_plain and abs(z1 - z1_plain) < 0.01  # gamma 1.0: as without
    assert min(share_plain, share_set, share_table) >= share1 - 0.01
    assert gross1 == gross_plain == gross_set == gross_table == 0
    assert 0.9 < z1 < 1.1 and 0.9 < z_table < 1.1
    assert 0.85 < z_set < 1.15
    assert 1.1 < z_plain < 1.4
