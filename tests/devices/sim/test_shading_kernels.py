"""The precompute's numba kernels (shading_kernels) against the numpy expressions they
replaced, kept here as references: the results must be bit-identical, so the twin's frames
and every accuracy figure measured on them stay as they were."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from app.devices.sim import SimulatedWorld
from app.devices.sim.optics import mat3, mat3_shifted, rig_by_name
from app.devices.sim.radiometry import (
    MATERIALS,
    REFLECTANCE,
    SPECULAR,
    SSS_MM,
    defocus_sigma_px,
    material_id,
)
from app.devices.sim.raycast import raycast_capsule, raycast_heightfield, raycast_sphere
from app.devices.sim.render import Renderer
from app.devices.sim.scenes import build_scene, sim_board
from app.devices.sim.scenes.base import Scene
from app.devices.sim.scenes.targets import BLACK, board_poses, board_printer, board_scene
from app.devices.sim.trace import BACKGROUND, Hits, trace

F64 = npt.NDArray[np.float64]


def _mat3_reference(points: F64, m: F64) -> F64:
    """The numpy broadcast ``mat3`` was before its kernel."""
    p = np.asarray(points, np.float64)
    if m.ndim == 1:
        out: F64 = p[..., 0] * m[0] + p[..., 1] * m[1] + p[..., 2] * m[2]
    else:
        out = p[..., 0, None] * m[0] + p[..., 1, None] * m[1] + p[..., 2, None] * m[2]
    return out


def _shade_reference(r: Renderer, points: F64, normals: F64, material: npt.NDArray[np.uint8],
                     albedo: F64, sigma_cam: F64, grad_xp: F64, led: str) -> tuple[F64, F64]:
    """``Renderer.shade`` as it was in numpy (einsum dot products, the projector test through
    ``to_projector``), before its per-pixel geometry became a kernel."""
    proj = r.rig.projector
    k = np.asarray(r.schedule.frequencies, np.float64)
    wp = r.schedule.width
    to_p = proj.centre - points
    d_p = np.sqrt(np.einsum("ij,ij->i", to_p, to_p))
    light = to_p / d_p[:, None]
    nrm = np.array(normals, copy=True)
    flip = np.einsum("ij,ij->i", nrm, points) > 0
    nrm[flip] *= -1
    cos_i = np.clip(np.einsum("ij,ij->i", nrm, light), 0.0, None)
    view = -points / np.sqrt(np.einsum("ij,ij->i", points, points))[:, None]
    half = light + view
    half /= np.sqrt(np.einsum("ij,ij->i", half, half))[:, None]
    cos_h = np.clip(np.einsum("ij,ij->i", nrm, half), 0.0, None)
    names = [MATERIALS[m] for m in range(len(MATERIALS))]
    refl = np.array([REFLECTANCE[n][led] for n in names])[material] * albedo
    ks = np.array([SPECULAR.get(n, (0.0, 1.0))[0] for n in names])[material]
    shin = np.array([SPECULAR.get(n, (0.0, 1.0))[1] for n in names])[material]
    sss = np.array([SSS_MM.get(n, {}).get(led, 0.0) for n in names])[material]
    g_d = refl * cos_i / d_p**2
    g_s = np.where(cos_i > 0, 0.05 * ks * cos_h**shin, 0.0) / d_p**2
    q = _mat3_reference(points - proj.centre, proj.R)
    with np.errstate(divide="ignore", invalid="ignore"):
        xp = proj.K[0, 0] * q[:, 0] / q[:, 2] + proj.K[0, 2]
        yp = proj.K[1, 1] * q[:, 1] / q[:, 2] + proj.K[1, 2]
    front = q[:, 2] > 0
    lit = front & (xp >= -0.5) & (xp <= wp - 0.5) & (yp >= -0.5) & (yp <= proj.size[1] - 0.5)
    lit &= np.isfinite(points).all(axis=1)
    g_d = np.where(lit, g_d, 0.0)
    g_s = np.where(lit, g_s, 0.0)
    z = points[:, 2]
    f_px = r.rig.camera.K[0, 0]
    sig_p = defocus_sigma_px(d_p, r.rig.projector_focus_mm, r.rig.projector_blur_per_inv_mm)
    sig_p_cam = sig_p / np.maximum(grad_xp, 1e-6)
    var_s = sigma_cam**2 + sig_p_cam**2
    var_d = var_s + (sss * f_px / z) ** 2
    ang = (2 * math.pi * k[:, None] * grad_xp[None] / r.schedule.axis_length) ** 2 / 2.0
    fringe = g_d[None] * np.exp(-ang * var_d[None]) + g_s[None] * np.exp(-ang * var_s[None])
    base = g_d + g_s
    return np.nan_to_num(base), np.nan_to_num(fringe)


def _bilinear_reference(grid: F64, s0: float, t0: float, ds: float, s: F64, t: F64) -> F64:
    ny, nx = grid.shape
    fx = np.clip((s - s0) / ds, 0, nx - 1 - 1e-9)
    fy = np.clip((t - t0) / ds, 0, ny - 1 - 1e-9)
    ix, iy = fx.astype(int), fy.astype(int)
    ax, ay = fx - ix, fy - iy
    out: F64 = ((1 - ay) * ((1 - ax) * grid[iy, ix] + ax * grid[iy, ix + 1])
                + ay * ((1 - ax) * grid[iy + 1, ix] + ax * grid[iy + 1, ix + 1]))
    return out


def _trace_reference(scene: Scene, dirs: F64, t_s: float = 0.0, *, with_tool: bool = True
                     ) -> Hits:
    """``trace`` as it was in numpy (boolean-mask gathers, the height field's normals, material
    and albedo in separate passes), before its per-ray part became a kernel."""
    delta = scene.offset(t_s)
    origin = -delta
    n = dirs.shape[0]
    hf = scene.surface
    t_hit = raycast_heightfield(origin, dirs, hf.origin, hf.axes, hf.heights, hf.s0, hf.t0, hf.ds,
                                hf.hmin, hf.hmax)
    points = origin + t_hit[:, None] * dirs
    loc = _mat3_reference(points - hf.origin, hf.axes)
    s, t = loc[:, 0], loc[:, 1]
    ok = np.isfinite(t_hit)
    normals = np.full((n, 3), np.nan)
    material = np.full(n, BACKGROUND, np.uint8)
    albedo = np.ones(n)
    if np.ptp(hf.heights) > 0:
        # np.gradient returns d/d(row) first: rows are t, columns s.
        dh_dt, dh_ds = (np.asarray(g, np.float64) for g in np.gradient(hf.heights, hf.ds))
        hs = _bilinear_reference(dh_ds, hf.s0, hf.t0, hf.ds, s[ok], t[ok])
        ht = _bilinear_reference(dh_dt, hf.s0, hf.t0, hf.ds, s[ok], t[ok])
        nl = np.stack([-hs, -ht, np.ones_like(hs)], -1)
        nl /= np.linalg.norm(nl, axis=1, keepdims=True)
        normals[ok] = _mat3_reference(nl, hf.axes.T)
    else:
        normals[ok] = hf.axes[:, 2]
    ny, nx = hf.heights.shape
    ix = np.clip(np.rint((s[ok] - hf.s0) / hf.ds).astype(int), 0, nx - 1)
    iy = np.clip(np.rint((t[ok] - hf.t0) / hf.ds).astype(int), 0, ny - 1)
    material[ok] = hf.material[iy, ix]
    albedo[ok] = _bilinear_reference(hf.texture.astype(np.float64), hf.s0, hf.t0, hf.ds, s[ok],
                                     t[ok])
    st = np.full((n, 2), np.nan)
    st[ok] = loc[ok, :2]
    best = np.where(ok, t_hit, np.inf)
    for sph in scene.spheres:
        ts = raycast_sphere(origin, dirs, sph.centre, sph.radius_mm)
        closer = np.isfinite(ts) & (ts < best)
        best[closer] = ts[closer]
        p = origin + ts[closer, None] * dirs[closer]
        points[closer] = p
        normals[closer] = (p - sph.centre) / sph.radius_mm
        material[closer] = material_id(sph.material)
        albedo[closer] = 1.0
        st[closer] = np.nan
    if with_tool and scene.tool is not None:
        p0, p1 = scene.tool.path(t_s)
        tt, nn = raycast_capsule(np.zeros(3), dirs, p0, p1, scene.tool.radius_mm)
        # origin −δ plus δ back: a ray parameter is the same in the camera frame, so compare
        # directly
        closer = np.isfinite(tt) & (tt < best)
        points[closer] = tt[closer, None] * dirs[closer] - delta
        normals[closer] = nn[closer]
        material[closer] = material_id(scene.tool.material)
        albedo[closer] = 1.0
        st[closer] = np.nan
        best[closer] = tt[closer]
    hit = np.isfinite(best)
    points[~hit] = np.nan
    return Hits(points + delta, normals, material, albedo, st)


def test_mat3_is_bit_identical_to_the_numpy_sums() -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(40, 57, 3)) * 30.0
    points[3, 4] = np.nan
    points[5, 6, 2] = np.inf
    m = rng.normal(size=(3, 3))
    shift = rng.normal(size=3)
    np.testing.assert_array_equal(mat3(points, m), _mat3_reference(points, m))
    np.testing.assert_array_equal(mat3(points, m[:, 1]), _mat3_reference(points, m[:, 1]))
    np.testing.assert_array_equal(mat3(points, m[:, :2]), _mat3_reference(points, m[:, :2]))
    np.testing.assert_array_equal(mat3_shifted(points, shift, m),
                                  _mat3_reference(points - shift, m))
    # a non-contiguous view (the renderer passes slices of its point image)
    view = points[:, ::2]
    np.testing.assert_array_equal(mat3(view, m), _mat3_reference(view, m))
    assert mat3(points, m[:, 1]).shape == (40, 57)


@pytest.mark.parametrize(("scene", "rig"), [("anastomosis", "default"),
                                            ("dof_target", "endoscope-projector-defect")])
def test_shade_is_bit_identical_to_the_numpy_expression(scene: str, rig: str) -> None:
    """Every pixel of a tissue scene (specular, subsurface, unlit background) and of a printed
    target on another rig, under two LEDs: base and fringe parts equal to the last bit."""
    r = SimulatedWorld(scene, seed=1, rig=rig).renderer
    pts = r.points.reshape(-1, 3)
    safe = np.where(np.isfinite(pts), pts, np.array([0.0, 0.0, 1e6]))
    for led in ("green", "red"):
        args = (safe, np.nan_to_num(r._normals), r._material, r.albedo, r.sigma_cam.ravel(),
                r.grad_xp, led)
        base, fringe = r.shade(*args)
        base_ref, fringe_ref = _shade_reference(r, *args)
        assert 0 < np.count_nonzero(base) < base.size  # lit and unlit pixels both tested
        np.testing.assert_array_equal(base, base_ref)
        np.testing.assert_array_equal(fringe, fringe_ref)


def test_checkerboard_print_matches_the_numpy_expression() -> None:
    """The board printer's kernel prints the same squares as the numpy expression it replaced,
    on and around the print, at square edges and off the board (NaN)."""
    spec = sim_board("checkerboard")
    p = spec.pitch_mm
    half_s, half_t = (spec.cols + 1) * p / 2, (spec.rows + 1) * p / 2

    def reference(s: F64, t: F64) -> F64:
        inside = (np.abs(s) < half_s) & (np.abs(t) < half_t)
        parity = (np.floor((s + half_s) / p) + np.floor((t + half_t) / p)) % 2
        out: F64 = np.where(inside & (parity == 0), BLACK, 1.0)
        return out

    rng = np.random.default_rng(5)
    s = rng.uniform(-1.3 * half_s, 1.3 * half_s, (5000, 8))
    t = rng.uniform(-1.3 * half_t, 1.3 * half_t, (5000, 8))
    edges = (np.arange(-spec.cols - 2, spec.cols + 3) * p / 2)[:, None]
    s[: edges.size, :2] = edges  # exactly on square edges and the print's border
    t[: edges.size, 2:4] = edges
    s[-10:, 0] = np.nan
    t[-20:-10, 1] = np.nan
    printed = board_printer(spec)(s, t)
    np.testing.assert_array_equal(printed, reference(s, t))
    assert {BLACK, 1.0} == set(np.unique(printed))
    # broadcast arguments, as a print function accepts
    np.testing.assert_array_equal(board_printer(spec)(s[:, :1], t[:1]),
                                  reference(s[:, :1], t[:1]))


@pytest.mark.parametrize("scene", ["anastomosis", "dof_target", "intestine_pile", "board"])
def test_trace_is_bit_identical_to_the_numpy_expression(scene: str) -> None:
    """Height field with slopes, spheres and a tool (tissue scenes), a flat printed target and a
    tilted calibration board: every output of every ray equal to the last bit. Every 5th
    pixel's ray (the kernel treats each ray on its own; a fifth keeps the test quick)."""
    rig = rig_by_name("default")
    if scene == "board":
        spec = sim_board("checkerboard")
        built = board_scene(rig, spec, board_poses(rig, 3, seed=2)[2])
    else:
        built = build_scene(scene, rig)
    rays = np.ascontiguousarray(rig.camera.pixel_rays().reshape(-1, 3)[::5])
    for t_s in (0.0, 0.4):
        got, want = trace(built, rays, t_s), _trace_reference(built, rays, t_s)
        for name in ("points", "normals", "material", "albedo", "st"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        assert np.isfinite(got.points).all(axis=1).any()  # surface hits were compared
