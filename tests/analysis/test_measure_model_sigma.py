"""A measurement's calibration σ from the depth model's own covariance (its jackknife over board
poses), correlated between points as the calibration's errors are."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.analysis import measure as M
from app.core.calibration import Calibration
from app.devices.sim.analytic_rig import bump_surface
from app.recon import Reconstructor
from app.recon.reconstructor import SensorNoise
from tests.helpers.analytic_models import band_fitted_calibration
from tests.helpers.calibrated_lengths import calibrated_length


@pytest.fixture(scope="module")
def scene() -> tuple[Calibration, object]:
    rig, cal = band_fitted_calibration(seed=11)  # valid columns ≳ 90
    frames = rig.render(bump_surface(rig), background=110.0, amplitude=90.0, noise=1.0)
    return cal, Reconstructor(cal, noise=SensorNoise(0.5, 4.0)).run(frames)


def _jackknife_sigma_of_length(
    cal: Calibration, res: object, a: tuple[int, int], b: tuple[int, int]
) -> float:
    """σ of the length from the leave-one-pose-out models themselves: each maps the phase the
    active model gives at the two points to heights, the points move along their rays."""
    model = cal.model
    plane = cal.reference_plane
    pts = np.array([res.points[v, u] for u, v in (a, b)], np.float64)  # type: ignore[attr-defined]
    uv = np.array([a, b], np.float64)
    ray = pts[:, :2] / pts[:, 2:3]
    h = pts @ cal.plane_normal + cal.plane_offset_mm
    phi = model.phase_at(uv[:, 0], uv[:, 1], ray, h, plane)
    r3 = np.concatenate([ray, np.ones((2, 1))], axis=1)

    def length_of(m: object) -> float:
        hm = m.height_at(uv[:, 0], uv[:, 1], ray, phi, plane)  # type: ignore[attr-defined]
        x = r3 * ((hm - plane.offset_mm) / (r3 @ plane.normal))[:, None]
        return float(np.linalg.norm(x[1] - x[0]))

    lengths = np.array([length_of(m) for m in model.jackknife])
    g = len(lengths)
    var = (g - 1) / g * float(np.sum((lengths - lengths.mean()) ** 2))
    var += (length_of(model.alternative) - float(np.linalg.norm(pts[1] - pts[0]))) ** 2
    return math.sqrt(var)


@pytest.mark.parametrize(
    "a, b", [((95, 10), (155, 110)), ((100, 60), (150, 60)), ((120, 60), (123, 60))]
)
def test_length_calibration_sigma_is_the_jackknife_spread_of_lengths(scene, a, b):
    cal, res = scene
    assert res.valid[a[1], a[0]] and res.valid[b[1], b[0]]
    m = calibrated_length(res, cal, [a, b])
    want = _jackknife_sigma_of_length(cal, res, a, b)
    assert want > 0
    assert m.extra["sigma_calibration_mm"] == pytest.approx(want, rel=0.02, abs=1e-6)
    assert m.sigma_mm == pytest.approx(
        math.hypot(m.extra["sigma_noise_mm"], m.extra["sigma_calibration_mm"])
    )


def test_nearby_points_share_most_of_the_calibration_error(scene):
    """Two points 3 px apart: the length's calibration σ is far below what independent errors of
    the two points' σ_model would give (√2·σ_model); the same points as independent would not."""
    cal, res = scene
    a, b = (120, 60), (123, 60)
    m = calibrated_length(res, cal, [a, b])
    sm = res.sigma_model
    independent = math.hypot(float(sm[a[1], a[0]]), float(sm[b[1], b[0]]))
    assert independent > 1e-3
    assert m.extra["sigma_calibration_mm"] < 0.1 * independent


def test_noise_part_is_independent_between_pixels(scene):
    """The noise part uses ``sigma`` as given (here the noise map): as without a calibration."""
    cal, res = scene
    pix = [(95, 10), (155, 110)]
    with_cal = calibrated_length(res, cal, pix)
    without = M.length(res.points, res.valid, res.sigma_noise, pix, plane_normal=cal.plane_normal)
    assert with_cal.extra["sigma_noise_mm"] == pytest.approx(without.sigma_mm, rel=1e-9)
    assert without.extra["sigma_calibration_mm"] == 0.0


@pytest.mark.parametrize(
    "kind, pixels",
    [
        ("depth", [(95, 10), (155, 10), (125, 110), (125, 60)]),
        ("point_to_line", [(95, 10), (155, 110), (130, 30)]),
        ("area", [(100, 30), (150, 30), (150, 90), (100, 90)]),
        ("profile", [(95, 60), (155, 60)]),
    ],
)
def test_every_kind_takes_the_calibration_covariance(scene, kind, pixels):
    cal, res = scene
    m = M.measure(
        kind,
        res.points,
        res.valid,
        res.sigma_noise,
        pixels,
        plane_normal=cal.plane_normal,
        calibration=cal,
    )
    s = m.extra["sigma_calibration_mm"]
    assert math.isfinite(s) and s > 0.0
    assert m.sigma_mm >= m.extra["sigma_noise_mm"]
