"""Radiometry: exposure, LED colour, noise model, saturation, bit depth."""

from __future__ import annotations

import numpy as np

from app.devices.sim.radiometry import LED_FLUX, REFLECTANCE, SENSOR_QE, SensorModel


def test_signal_monotonic_and_linear_in_exposure(plane_world):
    r = plane_world.renderer
    means = [r.mean_frame(0, 0.0, exposure_ms=e) for e in (5.0, 10.0, 20.0, 40.0)]
    lit = r.mean_frame(0, 0.0, exposure_ms=5.0) > 2.0
    assert lit.mean() > 0.5
    for a, b in zip(means, means[1:], strict=False):
        assert np.all(b[lit] > a[lit])
    # everything (light and ambient) scales with exposure
    np.testing.assert_allclose(means[3][lit], 8.0 * means[0][lit], rtol=1e-4)


def test_led_colours_follow_flux_qe_and_reflectance(plane_world):
    r = plane_world.renderer
    sens = r.sensor
    amb = {
        led: r.scales(exposure_ms=20.0, gain=1.0, led=led, current=0.5, bits=8)[1]
        for led in LED_FLUX
    }
    sig = {led: r.mean_frame(2, 0.0, exposure_ms=20.0, led=led) - amb[led] for led in LED_FLUX}
    lit = sig["green"] > 5.0
    for led in ("red", "blue"):
        expect = (LED_FLUX[led] * SENSOR_QE[led] * REFLECTANCE["grey"][led]) / (
            LED_FLUX["green"] * SENSOR_QE["green"] * REFLECTANCE["grey"]["green"])
        ratio = sig[led][lit] / sig["green"][lit]
        np.testing.assert_allclose(ratio, expect, rtol=1e-4)
    # Green gives the strongest signal on pigmented tissue relative to red/blue fringe loss:
    assert REFLECTANCE["intestine"]["green"] * sens.photons_scale > 0


def test_noise_statistics_match_model(plane_world):
    r = plane_world.renderer
    gain, bits, exposure = 4.0, 12, 20.0
    state = np.array([12345], np.uint64)
    frames = np.stack([r.render(5, 0.0, state, exposure_ms=exposure, gain=gain, bits=bits)
                       for _ in range(48)]).astype(np.float64)
    mean_model = r.mean_frame(5, 0.0, exposure_ms=exposure, gain=gain, bits=bits).astype(np.float64)
    sigma_model = plane_world.noise_sigma(mean_model, bits=bits, gain=gain)
    ok = (mean_model > 100) & (mean_model < 3500)
    sub = np.zeros_like(ok)
    sub[::7, ::7] = True
    ok &= sub
    assert ok.sum() > 5000
    m = frames[:, ok].mean(0)
    var = frames[:, ok].var(0, ddof=1)
    # unbiased: the mean error is within a few standard errors
    z = (m - mean_model[ok]) / (sigma_model[ok] / np.sqrt(frames.shape[0]))
    assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1
    ratio = var / sigma_model[ok] ** 2
    assert abs(ratio.mean() - 1.0) < 0.02
    # a pure-Gaussian draw: fraction beyond 2σ ≈ 4.6 %
    resid = (frames[:, ok] - mean_model[ok]) / sigma_model[ok]
    assert 0.040 < np.mean(np.abs(resid) > 2) < 0.052


def test_saturation_and_bit_depths(plane_world):
    r = plane_world.renderer
    state = np.array([7], np.uint64)
    f8 = r.render(0, 0.0, state, exposure_ms=100.0, gain=16.0, bits=8)
    assert f8.dtype == np.uint8 and f8.max() == 255 and np.mean(f8 == 255) > 0.3
    f12 = r.render(0, 0.0, state, exposure_ms=100.0, gain=16.0, bits=12)
    assert f12.dtype == np.uint16 and f12.max() == 4095
    dark = r.render(-1, 0.0, state, exposure_ms=1.0, bits=12)
    assert dark.mean() < 10  # projector off: ambient + read noise only


def test_noise_sigma_formula():
    s = SensorModel()
    g = s.dn_per_electron(8, 1.0)
    assert np.isclose(s.noise_sigma(100.0), np.sqrt(g * 100 + (g * s.read_noise_e) ** 2 + 1 / 12))
