"""Per-frame numba kernels for scenes with a tool (the forceps): its image rows, its
ray–capsule hits, shading and fringes, drawn over the moving scene row by row.

The scene rows, noise and ADC are :mod:`app.devices.sim.kernels`'; the tool's pixels are
found and shaded in a few simple passes per row so that LLVM vectorises each of them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
import numpy.typing as npt

from app.devices.sim.kernels import DN, F32, FAST, I32, I64, U64, _adc_run, _deviates, _scene_row

F64 = npt.NDArray[np.float64]
Vec3 = tuple[float, float, float]  # a 3-vector as loop-invariant scalars (see _tool_span)


@nb.njit(cache=True, error_model="numpy")
def tool_spans(sx: F64, sy: F64, v0: int, v1: int, rad_px: float, w: int) -> I64:
    """First/last column (v1 − v0 + 1, 2) int64 of rows v0 .. v1 covered by discs of radius rad_px
    (px) at the samples (sx, sy) (n,) px, clipped to 0 .. w − 1 (first > last: none).
    Not fastmath: the same spans as the numpy formulation in render.py used to give."""
    spans = np.empty((v1 - v0 + 1, 2), np.int64)
    r2 = rad_px * rad_px
    for i in range(v1 - v0 + 1):
        lo, hi = math.inf, -math.inf
        for k in range(sx.shape[0]):
            dy = (v0 + i) - sy[k]
            half = math.sqrt(max(r2 - dy * dy, 0.0))
            if half > 0.0:
                lo = min(lo, sx[k] - half)
                hi = max(hi, sx[k] + half)
        spans[i, 0] = int(min(max(math.floor(lo), 0.0), w - 1.0))
        spans[i, 1] = int(min(max(math.ceil(hi), -1.0), w - 1.0))
    return spans


class ToolFrame(NamedTuple):
    """The capsule tool at one instant, for :func:`tool_frame` (camera frame, mm).

    p0: (3,) first end; a_hat: (3,) unit axis; proj_c: (3,) projector centre;
    alpha, a_c, gam, g_c: projector column coefficients (optics.ProjectorModel.column_coefficients);
    refl, ks, shin: diffuse reflectance, specular weight and exponent of its material;
    two_pi_k_over_w, shift: fringe phase per projector column (rad) and phase shift (rad);
    atten: fringe contrast left after camera defocus; dz: depth offset (mm) of the scene
    behind it (the occlusion test uses the rest-pose depth of the same pixel + dz);
    rows_lit: whether the projector row of the tool lies on the DMD.
    """

    p0: npt.NDArray[np.float64]
    a_hat: npt.NDArray[np.float64]
    length: float
    radius: float
    refl: float
    ks: float
    shin: float
    proj_c: npt.NDArray[np.float64]
    alpha: npt.NDArray[np.float64]
    a_c: float
    gam: npt.NDArray[np.float64]
    g_c: float
    width_p: float
    rows_lit: bool
    two_pi_k_over_w: float
    shift: float
    atten: float
    dz: float


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _capsule_t(rx: float, ry: float, rz: float, p0: F64, a_hat: F64, length: float, radius: float
               ) -> tuple[float, float, float, float]:
    """Ray (from the origin, direction r) against a capsule; returns (t, nx, ny, nz) or t = inf.

    The capsule lies inside the infinite cylinder around its axis, so a ray that misses the
    cylinder misses it (no square root: most pixels of the tool's bounding box), and a
    cylinder entry point between the end discs is its first hit (the end spheres need no test).
    """
    ox, oy, oz = -p0[0], -p0[1], -p0[2]
    da = rx * a_hat[0] + ry * a_hat[1] + rz * a_hat[2]
    oa = ox * a_hat[0] + oy * a_hat[1] + oz * a_hat[2]
    dpx, dpy, dpz = rx - da * a_hat[0], ry - da * a_hat[1], rz - da * a_hat[2]
    opx, opy, opz = ox - oa * a_hat[0], oy - oa * a_hat[1], oz - oa * a_hat[2]
    a = dpx * dpx + dpy * dpy + dpz * dpz
    b = 2.0 * (dpx * opx + dpy * opy + dpz * opz)
    c = opx * opx + opy * opy + opz * opz - radius * radius
    disc = b * b - 4 * a * c
    if a > 0.0:
        if disc < 0.0:
            return math.inf, 0.0, 0.0, 0.0
        t = (-b - math.sqrt(disc)) / (2 * a)
        ax = oa + t * da
        if t > 0.0 and 0.0 <= ax <= length:
            return t, (opx + t * dpx) / radius, (opy + t * dpy) / radius, (opz + t * dpz) / radius
    best = math.inf
    bx = by = bz = 0.0
    for e in range(2):
        cx = p0[0] + e * length * a_hat[0]
        cy = p0[1] + e * length * a_hat[1]
        cz = p0[2] + e * length * a_hat[2]
        bb = -2.0 * (rx * cx + ry * cy + rz * cz)
        cc = cx * cx + cy * cy + cz * cz - radius * radius
        aa = rx * rx + ry * ry + rz * rz
        d2 = bb * bb - 4 * aa * cc
        if d2 >= 0.0:
            t = (-bb - math.sqrt(d2)) / (2 * aa)
            if 0.0 < t < best:
                best = t
                bx, by, bz = t * rx - cx, t * ry - cy, t * rz - cz
    return best, bx / radius, by / radius, bz / radius


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _pow(x: float, e: float) -> float:
    """x**e for x ≥ 0; by repeated squaring for a small whole e (specular
    exponents: ~7× faster than pow)."""
    if e == int(e) and 0 <= e < 1024:
        n = int(e)
        y = 1.0
        while n:
            if n & 1:
                y *= x
            x *= x
            n >>= 1
        return y
    p: float = x**e  # float ** float is Any in typeshed (a negative base gives a complex)
    return p


# fdlibm kernel coefficients of sin and cos on [−π/4, π/4] (|error| < 1e-16).
_S = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
      2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
      -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _cos(x: float) -> float:
    """cos(x) (rad) to ~1e-15 for |x| ≲ 1e3; branch-free so that the loops calling it vectorise
    (math.cos is a scalar libm call). Quadrant reduction, then the fdlibm polynomials."""
    q = math.floor(x * (2.0 / math.pi) + 0.5)
    r = x - q * (math.pi / 2.0)
    z = r * r
    s = r + r * z * (_S[0] + z * (_S[1] + z * (_S[2] + z * (_S[3] + z * (_S[4] + z * _S[5])))))
    c_hi = _C[3] + z * (_C[4] + z * _C[5])
    c = 1.0 - 0.5 * z + z * z * (_C[0] + z * (_C[1] + z * (_C[2] + z * c_hi)))
    n = int(q) & 3
    v = c if n & 1 == 0 else s
    return v if n == 0 or n == 3 else -v


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _pow_bits(x: float, n: int) -> float:
    """x**n for x ≥ 0 and a whole 0 ≤ n < 1024: the products of _pow, unrolled (no loop, so
    the loops calling it vectorise)."""
    y = 1.0
    y = y * x if n & 1 else y
    x *= x
    y = y * x if n & 2 else y
    x *= x
    y = y * x if n & 4 else y
    x *= x
    y = y * x if n & 8 else y
    x *= x
    y = y * x if n & 16 else y
    x *= x
    y = y * x if n & 32 else y
    x *= x
    y = y * x if n & 64 else y
    x *= x
    y = y * x if n & 128 else y
    x *= x
    y = y * x if n & 256 else y
    x *= x
    return y * x if n & 512 else y


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _cylinder(rx: float, ry: float, rz: float, p0: Vec3, a_hat: Vec3, radius: float
              ) -> tuple[float, float, float, float, float, float, float]:
    """The infinite-cylinder step of _capsule_t (same arithmetic): (a, disc, t, axial position,
    normal x, y, z); a hit needs a > 0, disc ≥ 0, t > 0 and 0 ≤ axial ≤ length."""
    ox, oy, oz = -p0[0], -p0[1], -p0[2]
    da = rx * a_hat[0] + ry * a_hat[1] + rz * a_hat[2]
    oa = ox * a_hat[0] + oy * a_hat[1] + oz * a_hat[2]
    dpx, dpy, dpz = rx - da * a_hat[0], ry - da * a_hat[1], rz - da * a_hat[2]
    opx, opy, opz = ox - oa * a_hat[0], oy - oa * a_hat[1], oz - oa * a_hat[2]
    a = dpx * dpx + dpy * dpy + dpz * dpz
    b = 2.0 * (dpx * opx + dpy * opy + dpz * opz)
    c = opx * opx + opy * opy + opz * opz - radius * radius
    disc = b * b - 4 * a * c
    t = (-b - math.sqrt(max(disc, 0.0))) / (2 * a)
    return (a, disc, t, oa + t * da, (opx + t * dpx) / radius, (opy + t * dpy) / radius,
            (opz + t * dpz) / radius)


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _cylinder_run(tt: F64, rx: F64, ry: F64, rz: F64, u0: int, u1: int, p0: Vec3, a_hat: Vec3,
                  length: float, radius: float) -> int:
    """tt[u] = ray parameter (mm) of the tool's cylinder hit of ray (rx, ry, rz)[u], u0 ≤ u ≤ u1;
    inf: miss, NaN: the end spheres decide (see _capsule_t). Returns the number of NaNs.

    All these run loops write one array and gather nothing: LLVM vectorises them then (not
    with a second output array or a table look-up)."""
    n_caps = 0
    for u in range(u0, u1 + 1):
        a, disc, t, ax, _, _, _ = _cylinder(rx[u], ry[u], rz[u], p0, a_hat, radius)
        hit = (a > 0.0) & (disc >= 0.0) & (t > 0.0) & (ax >= 0.0) & (ax <= length)
        caps = (not hit) & (not ((a > 0.0) & (disc < 0.0)))
        tt[u] = t if hit else (math.nan if caps else math.inf)
        n_caps += 1 if caps else 0
    return n_caps


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _light(t: float, rx: float, ry: float, rz: float, p0: Vec3, a_hat: Vec3, radius: float,
           pc: Vec3) -> tuple[float, float, float, float, float, float, float, float, float, float]:
    """Geometry of the cylinder hit at ray parameter t: (X, Y, Z) point, unit normal, unit
    direction to the projector and distance d (mm)."""
    _, _, _, _, nx, ny, nz = _cylinder(rx, ry, rz, p0, a_hat, radius)
    X, Y, Z = t * rx, t * ry, t * rz
    lx, ly, lz = pc[0] - X, pc[1] - Y, pc[2] - Z
    d = math.sqrt(lx * lx + ly * ly + lz * lz)
    return X, Y, Z, nx, ny, nz, lx / d, ly / d, lz / d, d


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _tool_index_run(kk: F64, tt: F64, rx: F64, ry: F64, rz: F64, zrow: F64, u0: int, u1: int,
                    p0: Vec3, a_hat: Vec3, radius: float, pc: Vec3, al: Vec3, a_c: float,
                    ga: Vec3, g_c: float, width_p: float, rows_lit: bool,
                    two_pi_k_over_w: float, shift: float, dz: float) -> None:
    """kk[u] = projector response table index (as float) of the cylinder hit tt[u] (_cylinder_run)
    where it is in front of the rest-pose depth zrow[u] + dz and lit; −9 where in front but
    unlit, NaN where not in front."""
    for u in range(u0, u1 + 1):
        t = tt[u]
        zs = zrow[u] + dz
        X, Y, Z, nx, ny, nz, lx, ly, lz, _ = _light(t, rx[u], ry[u], rz[u], p0, a_hat, radius, pc)
        cos_i = nx * lx + ny * ly + nz * lz
        xp = (al[0] * X + al[1] * Y + al[2] * Z - a_c) / (ga[0] * X + ga[1] * Y + ga[2] * Z - g_c)
        # & and not, not `and`/`or`: short-circuits leave branches that block vectorising
        front = (t != math.inf) & (not ((zs == zs) & (zs <= Z)))
        lit = (front & (not (cos_i <= 0.0)) & (not (xp < -0.5)) & (not (xp > width_p - 0.5))
               & rows_lit)
        p = 0.5 + 0.5 * _cos(two_pi_k_over_w * xp + shift)
        p = p if lit else 0.0  # a valid index where unlit (p may be NaN there)
        k = float(int(p * 255.0 + 0.5))
        kk[u] = k if lit else (-9.0 if front else math.nan)


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _tool_dn_run(out: F64, tt: F64, qq: F64, rx: F64, ry: F64, rz: F64, u0: int, u1: int,
                 p0: Vec3, a_hat: Vec3, radius: float, pc: Vec3, refl: float, ks: float,
                 n_shin: int, atten: float, qbar: float, scale: float, amb: float) -> None:
    """out[u] = DN of the cylinder hit tt[u] given qq[u] = projector output − qbar (lit), −9
    (unlit: ambient) or NaN (not in front: NaN); n_shin: the whole specular exponent."""
    for u in range(u0, u1 + 1):
        t, q = tt[u], qq[u]
        X, Y, Z, nx, ny, nz, lx, ly, lz, d = _light(t, rx[u], ry[u], rz[u], p0, a_hat, radius, pc)
        cos_i = nx * lx + ny * ly + nz * lz
        nv = math.sqrt(X * X + Y * Y + Z * Z)
        hx, hy, hz = lx - X / nv, ly - Y / nv, lz - Z / nv
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        cos_h = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
        base = (refl * cos_i + 0.05 * ks * _pow_bits(cos_h, n_shin)) / (d * d)
        m = scale * (base * qbar + atten * base * q) + amb
        out[u] = m if q > -5.0 else (amb if q == q else math.nan)


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _tool_pixel(rx: float, ry: float, rz: float, zs: float, tool: ToolFrame, lut: F32,
                qbar: float, scale: float, amb: float) -> float:
    """DN of the tool along ray (rx, ry, rz) in front of the scene at depth zs (NaN: none) by
    the full scalar capsule test (for the rays the vectorised cylinder passes leave out)."""
    (p0, a_hat, length, radius, refl, ks, shin, pc, al, a_c, ga, g_c, width_p, rows_lit,
     two_pi_k_over_w, shift, atten, dz) = tool
    t, nx, ny, nz = _capsule_t(rx, ry, rz, p0, a_hat, length, radius)
    zs = zs + dz
    if t == math.inf or (zs == zs and t * rz >= zs):
        return math.nan
    X, Y, Z = t * rx, t * ry, t * rz
    lx, ly, lz = pc[0] - X, pc[1] - Y, pc[2] - Z
    d = math.sqrt(lx * lx + ly * ly + lz * lz)
    lx, ly, lz = lx / d, ly / d, lz / d
    cos_i = nx * lx + ny * ly + nz * lz
    xp = (al[0] * X + al[1] * Y + al[2] * Z - a_c) / (ga[0] * X + ga[1] * Y + ga[2] * Z - g_c)
    if cos_i <= 0.0 or xp < -0.5 or xp > width_p - 0.5 or not rows_lit:
        return amb
    nv = math.sqrt(X * X + Y * Y + Z * Z)
    hx, hy, hz = lx - X / nv, ly - Y / nv, lz - Z / nv
    hn = math.sqrt(hx * hx + hy * hy + hz * hz)
    cos_h = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
    base = (refl * cos_i + 0.05 * ks * _pow(cos_h, shin)) / (d * d)
    p = 0.5 + 0.5 * math.cos(two_pi_k_over_w * xp + shift)
    dn: float = scale * (base * qbar + atten * base * (lut[int(p * 255.0 + 0.5)] - qbar)) + amb
    return dn


@nb.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def _tool_span(row: F32, sc: tuple[F64, F64, F64], v: int, u0: int, u1: int, rays: F64, zs: F64,
               tool: ToolFrame, lut: F32, qbar: float, scale: float, amb: float) -> None:
    """Overwrite row[u0 .. u1] (row ``v`` of the mean frame) where the tool is in front of the scene
    (its rest-pose depth zs (H, W) + tool.dz, NaN off-object). rays: (3, H, W) float64 planes of
    the unit pixel rays; sc: three (W,) float64 scratch rows (separate arrays: views of one 2-D
    array kept LLVM from vectorising the passes).

    Why passes: one scalar loop cost ~65 ns per tool pixel; the cylinder hits go through
    vectorised loops (cylinder, table index, DN) with only the table look-up scalar, the
    few rays the end spheres decide through the scalar _tool_pixel.
    """
    # (for mypy: the vectors are the tool's arrays first, then tuples of their components)
    p0: F64 | Vec3
    a_hat: F64 | Vec3
    pc: F64 | Vec3
    al: F64 | Vec3
    ga: F64 | Vec3
    # Fields as locals: LLVM keeps them in registers (field access in the loop is 2× slower).
    (p0, a_hat, length, radius, refl, ks, shin, pc, al, a_c, ga, g_c, width_p, rows_lit,
     two_pi_k_over_w, shift, atten, dz) = tool
    rx, ry, rz, zrow = rays[0, v], rays[1, v], rays[2, v], zs[v]
    tt, kk, dn = sc
    # Vectors as tuples: loop-invariant values, not memory the loops' stores might alias (too
    # many possible aliases and LLVM gives up vectorising).
    p0, a_hat, pc = (p0[0], p0[1], p0[2]), (a_hat[0], a_hat[1], a_hat[2]), (pc[0], pc[1], pc[2])
    al, ga = (al[0], al[1], al[2]), (ga[0], ga[1], ga[2])
    if _cylinder_run(tt, rx, ry, rz, u0, u1, p0, a_hat, length, radius):
        for u in range(u0, u1 + 1):
            if tt[u] != tt[u]:
                m = _tool_pixel(rx[u], ry[u], rz[u], zrow[u], tool, lut, qbar, scale, amb)
                row[u] = m if m == m else row[u]
                tt[u] = math.inf
    _tool_index_run(kk, tt, rx, ry, rz, zrow, u0, u1, p0, a_hat, radius, pc, al, a_c, ga, g_c,
                    width_p, rows_lit, two_pi_k_over_w, shift, dz)
    for u in range(u0, u1 + 1):  # the table look-up: a gather, scalar
        if kk[u] >= 0.0:
            kk[u] = lut[int(kk[u])] - qbar
    _tool_dn_run(dn, tt, kk, rx, ry, rz, u0, u1, p0, a_hat, radius, pc, refl, ks, int(shin), atten,
                 qbar, scale, amb)
    for u in range(u0, u1 + 1):
        if dn[u] == dn[u]:
            row[u] = dn[u]


@nb.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def tool_frame(out: F32 | DN, noisy: bool, row: F32, zbuf: F32, kk: I32, qv: F32, nd: F32,
               base: F32, fringe: F32, block_flow: I64, block: int, n_add: float, d_add: float,
               k_over_w: float, shift_frac: float, width_p: float, qtab: F32, qbar: float,
               scale: float, amb: float, g: float, read2: float, maxv: int, table: F32,
               state: U64, rays: F64, zs: F64, v0: int, spans: I64, tool: ToolFrame,
               lut: F32) -> None:
    """moving_frame with the capsule ``tool`` in front, row by row in raster order (the noise
    sequence of add_noise over the mean frame), so the mean frame is never stored.

    row: (W,) float32 scratch; rays: (3, H, W) float64 planes of the unit pixel rays; zs: (H, W)
    float64 rest-pose scene depth (mm, NaN off-object); spans: (n, 2) int first/last column to test
    in rows v0 .. v0 + n − 1 (the tool's image); tool: a ToolFrame; lut: projector response (256,).
    Other arguments as in moving_frame.
    """
    h, w = base.shape
    r = np.uint64(0)
    j = 4
    sc = (np.empty(w), np.empty(w), np.empty(w))  # _tool_span's scratch rows
    for v in range(h):
        _scene_row(row, kk, qv, v, nd, base, fringe, block_flow, block, n_add, d_add, k_over_w,
                   shift_frac, width_p, qtab, qbar, scale, amb)
        if v0 <= v < v0 + spans.shape[0]:
            _tool_span(row, sc, v, spans[v - v0, 0], spans[v - v0, 1], rays, zs, tool, lut, qbar,
                       scale, amb)
        if noisy:
            r, j = _deviates(zbuf, 0, w, table, state, r, j)
            _adc_run(out[v], row, zbuf, 0, w, g, read2, maxv)
        else:
            out[v, :] = row
