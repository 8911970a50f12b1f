"""Ray casting of the simulator's surfaces (numba): height fields, spheres, capsules.

All rays start at ``origin`` (camera frame, mm) with directions ``dirs`` (N, 3) and return
the ray parameter ``t`` of the first hit (NaN if none), so the hit is ``origin + t·dir``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


@nb.njit(cache=True, inline="always")
def _bilinear(grid: F64, s0: float, t0: float, ds: float, s: float, t: float) -> float:
    ny, nx = grid.shape
    fx = (s - s0) / ds
    fy = (t - t0) / ds
    if fx < 0.0 or fy < 0.0 or fx > nx - 1 or fy > ny - 1:
        return math.nan
    ix = min(int(fx), nx - 2)
    iy = min(int(fy), ny - 2)
    ax = fx - ix
    ay = fy - iy
    value: float = ((1 - ay) * ((1 - ax) * grid[iy, ix] + ax * grid[iy, ix + 1])
                    + ay * ((1 - ax) * grid[iy + 1, ix] + ax * grid[iy + 1, ix + 1]))
    return value


@nb.njit(cache=True, nogil=True)
def raycast_heightfield(origin: F64, dirs: F64, frame_origin: F64, axes: F64, heights: F64,
                        s0: float, t0: float, ds: float, hmin: float, hmax: float) -> F64:
    """First intersection of each ray with a height field over a plane frame.

    Args:
        frame_origin: (3,) plane origin; axes: (3, 3) columns e_s, e_t, n (n toward the scope).
        heights: (ny, nx) float64 heights (mm) along n at s = s0 + i·ds, t = t0 + j·ds.
        hmin, hmax: bounds of ``heights``.

    Returns:
        (N,) float64 ray parameter, NaN where the ray misses the grid.
    """
    n = dirs.shape[0]
    out = np.full(n, np.nan)
    ox = origin - frame_origin
    os_ = ox[0] * axes[0, 0] + ox[1] * axes[1, 0] + ox[2] * axes[2, 0]
    ot = ox[0] * axes[0, 1] + ox[1] * axes[1, 1] + ox[2] * axes[2, 1]
    ow = ox[0] * axes[0, 2] + ox[1] * axes[1, 2] + ox[2] * axes[2, 2]
    for i in range(n):
        d = dirs[i]
        ds_ = d[0] * axes[0, 0] + d[1] * axes[1, 0] + d[2] * axes[2, 0]
        dt = d[0] * axes[0, 1] + d[1] * axes[1, 1] + d[2] * axes[2, 1]
        dw = d[0] * axes[0, 2] + d[1] * axes[1, 2] + d[2] * axes[2, 2]
        if dw >= 0.0:
            continue
        ta = (hmax + 1e-9 - ow) / dw
        tb = (hmin - 1e-9 - ow) / dw
        if tb <= 0.0:
            continue
        ta = max(ta, 0.0)
        lateral = (tb - ta) * math.sqrt(ds_ * ds_ + dt * dt)
        steps = max(1, int(lateral / (0.5 * ds)) + 1)
        dtt = (tb - ta) / steps
        prev_t = ta
        prev_f = math.nan
        for k in range(steps + 1):
            tt = ta + k * dtt
            f = ow + tt * dw - _bilinear(heights, s0, t0, ds, os_ + tt * ds_, ot + tt * dt)
            if f <= 0.0:  # below the surface (NaN off-grid never matches)
                # starts under the surface or enters through a grid wall
                if k == 0 or not (prev_f > 0.0):
                    out[i] = tt
                    break
                lo, hi = prev_t, tt
                for _ in range(40):  # bisection-secant refinement to ~1e-9 mm
                    mid = 0.5 * (lo + hi)
                    fm = ow + mid * dw - _bilinear(heights, s0, t0, ds, os_ + mid * ds_,
                                                   ot + mid * dt)
                    if fm > 0.0:
                        lo = mid
                    else:
                        hi = mid
                    if hi - lo < 1e-10:
                        break
                out[i] = 0.5 * (lo + hi)
                break
            prev_t, prev_f = tt, f
    return out


def raycast_sphere(origin: npt.NDArray[np.float64], dirs: npt.NDArray[np.float64],
                   centre: npt.NDArray[np.float64], radius_mm: float) -> npt.NDArray[np.float64]:
    """Nearest positive ray parameter of a sphere, NaN where missed. dirs (N, 3)."""
    oc = origin - centre
    a = np.einsum("ij,ij->i", dirs, dirs)
    b = 2.0 * dirs @ oc
    c = oc @ oc - radius_mm**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore"):
        t: npt.NDArray[np.float64] = (-b - np.sqrt(disc)) / (2 * a)
    t[(disc < 0) | (t <= 0)] = np.nan
    return t


def raycast_capsule(origin: npt.NDArray[np.float64], dirs: npt.NDArray[np.float64],
                    p0: npt.NDArray[np.float64], p1: npt.NDArray[np.float64], radius_mm: float
                    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Ray parameter and outward unit normal (N, 3) for a capsule (cylinder
    p0→p1 with round ends)."""
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    a_hat = axis / length
    best = np.full(dirs.shape[0], np.nan)
    oc = origin - p0
    # Infinite cylinder, then keep hits whose axial coordinate is within the segment.
    d_perp = dirs - np.outer(dirs @ a_hat, a_hat)
    o_perp = oc - (oc @ a_hat) * a_hat
    a = np.einsum("ij,ij->i", d_perp, d_perp)
    b = 2.0 * d_perp @ o_perp
    c = o_perp @ o_perp - radius_mm**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    axial = (oc @ a_hat) + t * (dirs @ a_hat)
    ok = (disc >= 0) & (t > 0) & (axial >= 0) & (axial <= length)
    best[ok] = t[ok]
    for end in (p0, p1):
        ts = raycast_sphere(origin, dirs, end, radius_mm)
        better = np.isfinite(ts) & ~(ts >= best)
        best[better] = ts[better]
    hit = origin + best[:, None] * dirs
    rel = hit - p0
    along = np.clip(rel @ a_hat, 0.0, length)
    normal = rel - along[:, None] * a_hat
    with np.errstate(invalid="ignore"):
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return best, normal
