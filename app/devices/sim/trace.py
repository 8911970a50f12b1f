"""Scene tracing: per-pixel surface point, normal, material and area-integrated albedo."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.devices.sim.radiometry import material_id
from app.devices.sim.raycast import raycast_capsule, raycast_heightfield, raycast_sphere
from app.devices.sim.scenes.base import F64, HeightField, Scene
from app.devices.sim.shading_kernels import heightfield_hits

WHITE = material_id("white")
BACKGROUND = material_id("background")


@dataclass
class Hits:
    """Per-ray results, flattened (N, …). ``points`` NaN where nothing is hit."""

    points: F64
    normals: F64
    material: npt.NDArray[np.uint8]
    albedo: npt.NDArray[np.float64]
    st: F64  # (N, 2) surface coordinates on the height field (NaN elsewhere)


def trace(scene: Scene, dirs: F64, t_s: float = 0.0, *, with_tool: bool = True) -> Hits:
    """Trace rays from the camera centre through ``scene`` at time ``t_s`` (seconds).

    Rigid motion δ(t) is applied by tracing from the camera centre moved by −δ and adding δ
    back, which is exact. dirs: (N, 3) float64.
    """
    delta = scene.offset(t_s)
    origin = -delta
    n = dirs.shape[0]
    hf = scene.surface
    t_hit = raycast_heightfield(origin, dirs, hf.origin, hf.axes, hf.heights, hf.s0, hf.t0, hf.ds,
                                hf.hmin, hf.hmax)
    ok = np.isfinite(t_hit)
    sloped = bool(np.ptp(hf.heights) > 0)
    if sloped:
        # np.gradient returns d/d(row) first: rows are t, columns s.
        dh_dt, dh_ds = (np.asarray(g, np.float64) for g in np.gradient(hf.heights, hf.ds))
    else:
        dh_dt = dh_ds = np.zeros((1, 1))
    points, st, normals = np.empty((n, 3)), np.empty((n, 2)), np.empty((n, 3))
    material, albedo = np.empty(n, np.uint8), np.empty(n)
    # points, surface coordinates, normals, material and printed albedo in one pass per ray
    heightfield_hits(np.asarray(origin, np.float64), np.ascontiguousarray(dirs, np.float64),
                     t_hit, np.asarray(hf.origin, np.float64),
                     np.ascontiguousarray(hf.axes, np.float64), float(hf.s0), float(hf.t0),
                     float(hf.ds), np.ascontiguousarray(hf.material, np.uint8),
                     np.ascontiguousarray(hf.texture), dh_ds, dh_dt, sloped, points,
                     st, normals, material, albedo, int(BACKGROUND))
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


def integrate_print(hf: HeightField, st: F64, material: npt.NDArray[np.uint8],
                    shape: tuple[int, int], oversample: int = 8) -> F64:
    """Printed albedo averaged over each pixel's footprint, (H, W); 1 where nothing is printed.

    The footprint is the affine map of the pixel square through the local Jacobian of (s, t)
    (central differences of the pixel-centre hits). Pixels whose four corners agree are taken
    as uniform; the rest are supersampled ``oversample``² times — sharp edges stay sub-pixel exact.
    """
    h, w = shape
    out = np.ones((h, w))
    if hf.printed is None:
        return out
    s = st[:, 0].reshape(h, w)
    t = st[:, 1].reshape(h, w)
    printable = (material.reshape(h, w) == WHITE) & np.isfinite(s)
    with np.errstate(invalid="ignore"):
        dsu, dsv = np.gradient(s, axis=1), np.gradient(s, axis=0)
        dtu, dtv = np.gradient(t, axis=1), np.gradient(t, axis=0)
    jac_ok = np.isfinite(dsu) & np.isfinite(dsv) & np.isfinite(dtu) & np.isfinite(dtv)
    sel = printable & jac_ok
    sc, tc = s[sel], t[sel]
    j = (dsu[sel], dsv[sel], dtu[sel], dtv[sel])
    corners = [hf.printed(sc + 0.5 * (a * j[0] + b * j[1]), tc + 0.5 * (a * j[2] + b * j[3]))
               for a, b in ((-1, -1), (1, -1), (-1, 1), (1, 1))]
    centre = hf.printed(sc, tc)
    vals: npt.NDArray[np.float64] = centre.astype(np.float64)
    mixed = np.zeros(sc.shape, bool)
    for c in corners:
        mixed |= c != centre
    if mixed.any():
        off = (np.arange(oversample) + 0.5) / oversample - 0.5
        a, b = (g.ravel() for g in np.meshgrid(off, off))
        sm, tm = sc[mixed], tc[mixed]
        jm = [x[mixed] for x in j]
        ssub = sm[:, None] + a[None] * jm[0][:, None] + b[None] * jm[1][:, None]
        tsub = tm[:, None] + a[None] * jm[2][:, None] + b[None] * jm[3][:, None]
        vals[mixed] = hf.printed(ssub, tsub).mean(axis=1)
    out[sel] = vals
    return out
