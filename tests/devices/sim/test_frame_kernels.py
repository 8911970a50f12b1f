"""The fused per-frame kernels against plain numpy references of what they render.

The moving-scene kernels warp the rest-pose samples tile by tile, overlay the tool by an
exact ray–capsule test and add noise in one pass; these references do each step
separately and simply, so an optimisation of the kernels cannot change the pictures.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.devices.sim import SimulatedWorld, kernels, tool_kernels
from app.devices.sim.radiometry import gaussian_quantile_table
from app.devices.sim.render import BLOCK, Renderer

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def anastomosis() -> Renderer:
    return SimulatedWorld("anastomosis", seed=1).renderer


def _scene_reference(r: Renderer, pattern: int, t_s: float, scale: float, amb: float) -> np.ndarray:
    """Mean (H, W) float64 DN of the moved scene without its tool: per-tile integer flow, exact
    projector column of the moved sample, projector output from the one-period table."""
    h, w = r.shape
    fi, n = divmod(pattern, r.schedule.steps)
    base, fringe = (a.reshape(-1, h, w) for a in r._led_arrays("green"))
    alpha, _, gam, _ = r.rig.projector.column_coefficients()
    delta = r.scene.offset(t_s)
    flow = r._block_flow(delta)
    vv, uu = np.mgrid[0:h, 0:w]
    sv = np.clip(vv - flow[vv // BLOCK, uu // BLOCK, 1], 0, h - 1)
    su = np.clip(uu - flow[vv // BLOCK, uu // BLOCK, 0], 0, w - 1)
    nd = r._nd_table().astype(np.float64)
    b = base[0][sv, su].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        xp = (nd[0][sv, su] + alpha @ delta) / (nd[1][sv, su] + gam @ delta)
    lit = (b > 0) & (xp >= -0.5) & (xp <= r.schedule.width - 0.5)
    f = (
        np.where(lit, xp, 0.0) * r.schedule.frequencies[fi] / r.schedule.width
        + n / r.schedule.steps
        + 1.0
    )
    f -= np.floor(f)
    q = r.qtab[np.minimum((f * len(r.qtab)).astype(int), len(r.qtab) - 1)]
    m = scale * (b * r.qbar + fringe[fi][sv, su] * (q - r.qbar)) + amb
    return np.where(lit, m, amb)


def _capsule_reference(
    rays: np.ndarray, p0: np.ndarray, a_hat: np.ndarray, length: float, radius: float
) -> np.ndarray:
    """Ray parameter t (N,) of the first hit of rays (N, 3) from the camera with a capsule (inf:
    miss), tested against its cylinder and both end spheres."""
    da, oa = rays @ a_hat, -p0 @ a_hat
    dp, op = rays - da[:, None] * a_hat, -p0 - oa * a_hat
    a, b, c = np.einsum("ij,ij->i", dp, dp), 2 * dp @ op, op @ op - radius**2
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    ax = oa + t * da
    best = np.where((t > 0) & (ax >= 0) & (ax <= length), t, np.inf)
    for e in (0.0, length):
        centre = p0 + e * a_hat
        aa, bb, cc = (
            np.einsum("ij,ij->i", rays, rays),
            -2 * rays @ centre,
            centre @ centre - radius**2,
        )
        with np.errstate(invalid="ignore"):
            ts = (-bb - np.sqrt(bb * bb - 4 * aa * cc)) / (2 * aa)
        best = np.where((ts > 0) & (ts < best), ts, best)
    return best


def test_moving_scene_with_tool_matches_reference(anastomosis: Renderer):
    r = anastomosis
    t_s, pattern = 1.3, 6
    scale, amb, _, _, _ = r.scales(exposure_ms=20.0, gain=1.0, led="green", current=0.5, bits=8)
    mean = r.mean_frame(pattern, t_s, exposure_ms=20.0)
    ref = _scene_reference(r, pattern, t_s, scale, amb)
    # Where the tool is: an exact ray–capsule test per pixel, in front of the scene.
    p0, p1 = (np.asarray(p, np.float64) for p in r.scene.tool.path(t_s))
    length = float(np.linalg.norm(p1 - p0))
    h, w = r.shape
    t_hit = _capsule_reference(
        r.rays, p0, (p1 - p0) / length, length, r.scene.tool.radius_mm
    ).reshape(h, w)
    zs = r.points[..., 2] + r.scene.offset(t_s)[2]
    on_tool = np.isfinite(t_hit) & ~(t_hit * r.rays[:, 2].reshape(h, w) >= zs)
    assert 0.02 < on_tool.mean() < 0.3  # the forceps are in view at this instant
    np.testing.assert_allclose(mean[~on_tool], ref[~on_tool], rtol=1e-5, atol=0.02)
    # the tool covers the scene there (metal: bright, or dark where the light grazes it)
    assert np.mean(np.abs(mean[on_tool] - ref[on_tool]) > 1.0) > 0.5
    # silhouette pixels: allow rounding at grazing hits
    edge = on_tool ^ np.roll(on_tool, 1, axis=1)
    assert np.mean(mean[on_tool & ~edge] != ref[on_tool & ~edge]) > 0.5


@pytest.mark.parametrize("bits", [8, 12])
def test_noisy_frame_is_mean_plus_raster_noise(anastomosis: Renderer, bits: int):
    """The fused frame equals the stored-mean path: the mean frame, then add_noise in raster
    order."""
    r = anastomosis
    t_s, pattern = 0.7, 3
    state = np.array([987654321], np.uint64)
    frame = r.render(pattern, t_s, state.copy(), exposure_ms=20.0, bits=bits)
    _, _, g, read2, maxv = r.scales(exposure_ms=20.0, gain=1.0, led="green", current=0.5, bits=bits)
    mean = r.mean_frame(pattern, t_s, exposure_ms=20.0, bits=bits)
    ref = np.empty_like(frame)
    kernels.add_noise(
        ref.reshape(-1), mean.reshape(-1), g, read2, maxv, gaussian_quantile_table(), state.copy()
    )
    diff = np.abs(frame.astype(int) - ref.astype(int))
    # rounding of a few vectorised pixels at most
    assert diff.max() <= 1 and np.mean(diff > 0) < 1e-4
    assert frame.std() > 5 and math.isfinite(float(frame.mean()))


def test_vectorisable_cos_and_pow_match_scalar():
    """The tool passes' branch-free cos and whole power against math.cos and _pow."""
    x = np.random.default_rng(0).uniform(-600.0, 600.0, 20_000)
    assert max(abs(tool_kernels._cos(v) - math.cos(v)) for v in x) < 1e-12
    for e in (0, 1, 30, 60, 120, 1023):
        for v in x[:200] / 600.0 + 0.5:
            assert tool_kernels._pow_bits(v, e) == tool_kernels._pow(v, float(e))
