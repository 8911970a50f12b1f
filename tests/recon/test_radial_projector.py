"""A projector whose lens is radial (it bends each fringe along its length): the fused kernel and
the numpy path both follow each pixel's epipolar line, and agree with the truth and each other."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from app.calib.model import undistort_points
from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor
from app.recon.sensor import SensorNoise
from tests.helpers.analytic_models import geometric_of, projector_phase, rig_calibration

TOP = 4095  # 12-bit: the rounding noise stays far below the bending tested


def _frames(rig: Rig, phase_finest: np.ndarray) -> np.ndarray:
    """(F, H, W) uint16 noise-free fringe frames of the rig's schedule for the finest phase."""
    s = rig.schedule
    xp = phase_finest * s.width / (2.0 * math.pi * s.frequencies[-1])
    out = np.empty((s.n_frames, rig.height, rig.width), np.uint16)
    for fi, k in enumerate(s.frequencies):
        for n in range(s.steps):
            shift = 2 * math.pi * n / s.steps
            img = 1800.0 + 1500.0 * np.cos(2 * math.pi * k * xp / s.width + shift)
            out[s.frame_index(fi, n)] = np.clip(np.rint(img), 0, TOP).astype(np.uint16)
    return out


@pytest.fixture(scope="module")
def scene() -> tuple[Rig, np.ndarray, np.ndarray]:
    rig = Rig()
    truth = geometric_of(rig, k1=-0.05)
    height = bump_surface(rig)
    vv, uu = np.mgrid[: rig.height, : rig.width].astype(np.float64)
    rays = undistort_points(np.stack([uu.ravel(), vv.ravel()], 1), rig.K, np.zeros(5))
    r3 = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    off, normal = rig.plane_offset_mm, np.asarray(rig.n, np.float64)
    points = r3 * ((height.ravel() - off) / (r3 @ normal))[:, None]
    phase = projector_phase(truth, points).reshape(height.shape)
    return rig, height, _frames(rig, phase)


NOISE = SensorNoise(gain_dn_per_e=0.0, read_noise_dn=0.3)


@pytest.mark.parametrize("fast", [True, False])
def test_the_radial_model_recovers_the_heights_the_along_axis_model_misses(scene, fast):
    rig, height, frames = scene
    truth = geometric_of(rig, k1=-0.05)
    radial = Reconstructor(rig_calibration(rig, truth), noise=NOISE).run(
        frames, max_code=TOP, fast=fast)
    along = Reconstructor(rig_calibration(rig, replace(truth, k1_radial=False)), noise=NOISE).run(
        frames, max_code=TOP, fast=fast)
    ok = radial.valid & along.valid
    assert ok.mean() > 0.9
    err_radial = np.abs(radial.depth[ok].astype(np.float64) - height[ok])
    err_along = np.abs(along.depth[ok].astype(np.float64) - height[ok])
    assert np.percentile(err_radial, 99.9) < 0.01, np.percentile(err_radial, 99.9)
    assert np.max(err_along) > 0.1  # the bending across the fringes is what the kernel follows


def test_fast_and_numpy_agree_on_a_radial_lens(scene):
    rig, _, frames = scene
    rec = Reconstructor(rig_calibration(rig, geometric_of(rig, k1=-0.05)), noise=NOISE)
    a, b = rec.run(frames, max_code=TOP), rec.run(frames, max_code=TOP, fast=False)
    both = a.valid & b.valid
    assert both.mean() > 0.9 and np.mean(a.valid != b.valid) < 1e-3
    np.testing.assert_allclose(a.depth[both], b.depth[both], atol=2e-4)
    np.testing.assert_allclose(a.sigma[both], b.sigma[both], rtol=2e-3)
