"""Numba kernels of the renderer's once-per-scene precompute: small matrix products and the
per-pixel shading arithmetic.

They replace numpy expressions that made a temporary array per operation (a 1384 × 1032
image of 3-vectors is 34 MB per temporary). Each kernel evaluates the same IEEE operations in
the same order as the numpy expression it replaces and is compiled without fast-math (no
fused multiply-add, no reassociation), so its results are bit-identical; the transcendental
functions (``exp``, ``pow``) stay in numpy, whose SIMD versions numba's libm calls would not
match to the last bit.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def mat3_rows(p: F64, m: F64, out: F64) -> None:  # pragma: no cover - compiled
    """out[i, j] = p[i, 0]·m[0, j] + p[i, 1]·m[1, j] + p[i, 2]·m[2, j], summed left to right.

    p: (N, 3) float64; m: (3, k) float64; out: (N, k) float64.
    """
    k = m.shape[1]
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        for j in range(k):
            out[i, j] = x * m[0, j] + y * m[1, j] + z * m[2, j]


@nb.njit(cache=True, nogil=True)
def mat3_shifted_rows(p: F64, shift: F64, m: F64, out: F64) -> None:  # pragma: no cover
    """As :func:`mat3_rows` for the rows p[i] − shift ((3,) float64), without the (N, 3)
    difference array: the subtraction is rounded first, as numpy's would be."""
    k = m.shape[1]
    for i in range(p.shape[0]):
        x, y, z = p[i, 0] - shift[0], p[i, 1] - shift[1], p[i, 2] - shift[2]
        for j in range(k):
            out[i, j] = x * m[0, j] + y * m[1, j] + z * m[2, j]


@nb.njit(cache=True, nogil=True)
def shade_geometry(points: F64, normals: F64, centre: F64, rot: F64, kp: F64, width_p: float,
                   height_p: float, d_p: F64, cos_i: F64, cos_h: F64,
                   lit: npt.NDArray[np.bool_]) -> None:  # pragma: no cover - compiled
    """Per-point geometry of the projector light (see ``Renderer.shade``), one pass.

    Args:
        points: (N, 3) float64 camera-frame points, mm (finite).
        normals: (N, 3) float64 surface normals (any sign; turned to face the camera here).
        centre: (3,) float64 projector centre, mm; rot: (3, 3) float64 projector rotation (its
            frame's vectors to the camera frame's: a point's projector coordinates are
            (X − centre)·rot); kp: (3, 3) float64 projector intrinsics.
        width_p, height_p: extent (projector px) of the pattern along x and y.
        d_p: out (N,) float64 distance to the projector, mm.
        cos_i: out (N,) float64 cosine of incidence, ≥ 0 (NaN stays NaN, as np.clip).
        cos_h: out (N,) float64 cosine between normal and the half vector, ≥ 0.
        lit: out (N,) bool: in front of the projector, inside its pattern and finite.
    """
    # The dot products sum x, z, then y: the order of numpy's einsum("ij,ij->i") over rows of
    # three (two SIMD lanes), which the numpy expression used.
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        tx, ty, tz = centre[0] - px, centre[1] - py, centre[2] - pz
        d = math.sqrt(tx * tx + tz * tz + ty * ty)
        lx, ly, lz = tx / d, ty / d, tz / d
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        if nx * px + nz * pz + ny * py > 0:  # normals face the camera
            nx, ny, nz = -nx, -ny, -nz
        ci = nx * lx + nz * lz + ny * ly
        pn = math.sqrt(px * px + pz * pz + py * py)
        vx, vy, vz = -px / pn, -py / pn, -pz / pn
        hx, hy, hz = lx + vx, ly + vy, lz + vz
        hn = math.sqrt(hx * hx + hz * hz + hy * hy)
        hx, hy, hz = hx / hn, hy / hn, hz / hn
        ch = nx * hx + nz * hz + ny * hy
        d_p[i] = d
        cos_i[i] = 0.0 if ci < 0.0 else ci
        cos_h[i] = 0.0 if ch < 0.0 else ch
        # projector coordinates of the point: (X − centre)·rot
        qx = -tx * rot[0, 0] + -ty * rot[1, 0] + -tz * rot[2, 0]
        qy = -tx * rot[0, 1] + -ty * rot[1, 1] + -tz * rot[2, 1]
        qz = -tx * rot[0, 2] + -ty * rot[1, 2] + -tz * rot[2, 2]
        xp = kp[0, 0] * qx / qz + kp[0, 2]
        yp = kp[1, 1] * qy / qz + kp[1, 2]
        lit[i] = (qz > 0 and xp >= -0.5 and xp <= width_p - 0.5 and yp >= -0.5
                  and yp <= height_p - 0.5 and math.isfinite(px) and math.isfinite(py)
                  and math.isfinite(pz))


@nb.njit(cache=True, nogil=True)
def shade_terms(refl: F64, cos_i: F64, d_p: F64, spec: F64, lit: npt.NDArray[np.bool_],
                sigma_cam: F64, grad_xp: F64, sss: F64, z: F64, f_px: float, half_blur: float,
                inv_focus: float, two_pi_k: F64, axis_px: float, g_d: F64, g_s: F64,
                arg_d: F64, arg_s: F64) -> None:  # pragma: no cover - compiled
    """Diffuse and specular gains and the fringe attenuation exponents (see
    ``Renderer.shade``), one pass; the numpy expression's operations in its order.

    Args:
        refl: (N,) float64 reflectance × albedo; cos_i, d_p, lit: from :func:`shade_geometry`.
        spec: (N,) float64 specular lobe 0.05·k_s·cos_hˢʰⁱⁿ (pow in numpy).
        sigma_cam: (N,) float64 camera defocus σ, px; grad_xp: (N,) float64 projector px per
            camera px; sss: (N,) float64 subsurface scattering length, mm; z: (N,) float64 depth,
            mm; f_px: camera focal length, px.
        half_blur, inv_focus: 0.5 · the projector's blur per inverse mm and 1 / its focus (mm⁻¹).
        two_pi_k: (F,) float64 2π · fringe frequency (periods per axis); axis_px: the pattern's
            axis length, projector px.
        g_d, g_s: out (N,) float64 diffuse and specular gain, mm⁻² (0 where unlit).
        arg_d, arg_s: out (F, N) float64 exponents −(2πk·∇x_p/L)²/2 · σ² of the diffuse
            (camera + projector defocus + subsurface) and specular (defocus only) fringe parts.
    """
    n = refl.shape[0]
    var_s, var_d = np.empty(n), np.empty(n)
    for i in range(n):
        d2 = d_p[i] * d_p[i]
        gd = refl[i] * cos_i[i] / d2
        gs = (spec[i] if cos_i[i] > 0 else 0.0) / d2
        g_d[i] = gd if lit[i] else 0.0
        g_s[i] = gs if lit[i] else 0.0
        sig_p = half_blur * abs(1.0 / d_p[i] - inv_focus)
        g = grad_xp[i]
        sig_p_cam = sig_p / (g if g >= 1e-6 or g != g else 1e-6)  # np.maximum keeps NaN
        var_s[i] = sigma_cam[i] * sigma_cam[i] + sig_p_cam * sig_p_cam
        t = sss[i] * f_px / z[i]
        var_d[i] = var_s[i] + t * t
    # frequency-major: each row a contiguous, branch-free loop that vectorises
    for f in range(two_pi_k.shape[0]):
        tk = two_pi_k[f]
        row_d, row_s = arg_d[f], arg_s[f]
        for i in range(n):
            a = tk * grad_xp[i] / axis_px
            ang = a * a / 2.0
            row_d[i] = -ang * var_d[i]
            row_s[i] = -ang * var_s[i]


@nb.njit(cache=True, nogil=True, inline="always")
def _finite(x: float) -> float:  # pragma: no cover - compiled
    """np.nan_to_num of one value: NaN → 0, ±inf → ± the largest float64."""
    if x != x:
        return 0.0
    if x == math.inf:
        return 1.7976931348623157e308
    if x == -math.inf:
        return -1.7976931348623157e308
    return x


@nb.njit(cache=True, nogil=True)
def shade_combine(g_d: F64, g_s: F64, exp_d: F64, exp_s: F64, base: F64,
                  fringe: F64) -> None:  # pragma: no cover - compiled
    """base = nan_to_num(g_d + g_s) (N,), fringe = nan_to_num(g_d·exp_d + g_s·exp_s) (F, N),
    float64, from :func:`shade_terms`' gains and the exponentials of its exponents. ``fringe``
    may be ``exp_d`` itself (element by element, read before written)."""
    for i in range(g_d.shape[0]):
        base[i] = _finite(g_d[i] + g_s[i])
    for f in range(exp_d.shape[0]):
        row, e_d, e_s = fringe[f], exp_d[f], exp_s[f]
        for i in range(g_d.shape[0]):
            row[i] = _finite(g_d[i] * e_d[i] + g_s[i] * e_s[i])


@nb.njit(cache=True, nogil=True)
def checker_reflectance(s: F64, t: F64, half_s: float, half_t: float, pitch: float, black: float,
                        out: F64) -> None:  # pragma: no cover - compiled
    """out[i] = ``black`` on the dark squares of a checkerboard print, else 1.0.

    s, t: (N,) float64 board coordinates, mm (NaN: off the board, prints 1.0); the print spans
    |s| < half_s, |t| < half_t (mm) in squares of side ``pitch`` (mm), the one at the
    (−half_s, −half_t) corner dark. The same float operations as the numpy expression
    (floor, then Python's modulo of the sum), so the same squares.
    """
    for i in range(s.shape[0]):
        inside = abs(s[i]) < half_s and abs(t[i]) < half_t
        parity = (math.floor((s[i] + half_s) / pitch) + math.floor((t[i] + half_t) / pitch)) % 2
        out[i] = black if inside and parity == 0 else 1.0


@nb.njit(cache=True, inline="always")
def _bilinear_clamped(grid: npt.NDArray[np.floating], s0: float, t0: float, ds: float, s: float,
                      t: float) -> float:  # pragma: no cover - compiled
    """trace._bilinear_np for one point: the grid (ny, nx) at (s, t) mm, clamped to its edge."""
    ny, nx = grid.shape
    fx = min(max((s - s0) / ds, 0.0), nx - 1 - 1e-9)
    fy = min(max((t - t0) / ds, 0.0), ny - 1 - 1e-9)
    ix, iy = int(fx), int(fy)
    ax, ay = fx - ix, fy - iy
    g00, g01 = np.float64(grid[iy, ix]), np.float64(grid[iy, ix + 1])
    g10, g11 = np.float64(grid[iy + 1, ix]), np.float64(grid[iy + 1, ix + 1])
    value: float = (1 - ay) * ((1 - ax) * g00 + ax * g01) + ay * ((1 - ax) * g10 + ax * g11)
    return value


@nb.njit(cache=True, nogil=True)
def heightfield_hits(origin: F64, dirs: F64, t_hit: F64, frame_origin: F64, axes: F64,
                     s0: float, t0: float, ds: float, material_grid: npt.NDArray[np.uint8],
                     texture: npt.NDArray[np.floating], dh_ds: F64, dh_dt: F64, sloped: bool,
                     points: F64, st: F64, normals: F64, material: npt.NDArray[np.uint8],
                     albedo: F64, background: int) -> None:  # pragma: no cover - compiled
    """What ``trace`` derives from the height field's ray parameters, one pass per ray.

    Args:
        origin: (3,) float64 ray origin, mm; dirs: (N, 3) float64; t_hit: (N,) float64 (NaN: no
            hit). frame_origin (3,), axes (3, 3) (columns e_s, e_t, n), s0, t0, ds: the height
            field's frame and grid (mm); material_grid (ny, nx) uint8, texture (ny, nx)
            float (float32 in the scenes): its material codes and printed albedo.
        dh_ds, dh_dt: (ny, nx) float64 height slopes (np.gradient), read if ``sloped``;
            otherwise every normal is the frame's n.
        points: out (N, 3) float64 origin + t·dir (NaN where no hit); st: out (N, 2) float64
            surface coordinates (NaN where no hit); normals: out (N, 3) float64 (NaN where no
            hit); material: out (N,) uint8 (``background`` where no hit); albedo: out (N,)
            float64 (1 where no hit).
    """
    ny, nx = material_grid.shape
    for i in range(dirs.shape[0]):
        th = t_hit[i]
        px = origin[0] + th * dirs[i, 0]
        py = origin[1] + th * dirs[i, 1]
        pz = origin[2] + th * dirs[i, 2]
        points[i, 0], points[i, 1], points[i, 2] = px, py, pz
        if not math.isfinite(th):
            st[i, 0] = st[i, 1] = math.nan
            normals[i, 0] = normals[i, 1] = normals[i, 2] = math.nan
            material[i] = background
            albedo[i] = 1.0
            continue
        x, y, z = px - frame_origin[0], py - frame_origin[1], pz - frame_origin[2]
        s = x * axes[0, 0] + y * axes[1, 0] + z * axes[2, 0]
        t = x * axes[0, 1] + y * axes[1, 1] + z * axes[2, 1]
        st[i, 0], st[i, 1] = s, t
        if sloped:
            nl0 = -_bilinear_clamped(dh_ds, s0, t0, ds, s, t)
            nl1 = -_bilinear_clamped(dh_dt, s0, t0, ds, s, t)
            norm = math.sqrt(nl0 * nl0 + nl1 * nl1 + 1.0)
            nl0, nl1, nl2 = nl0 / norm, nl1 / norm, 1.0 / norm
            for j in range(3):
                normals[i, j] = nl0 * axes[j, 0] + nl1 * axes[j, 1] + nl2 * axes[j, 2]
        else:
            normals[i, 0], normals[i, 1], normals[i, 2] = axes[0, 2], axes[1, 2], axes[2, 2]
        ix = min(max(int(np.rint((s - s0) / ds)), 0), nx - 1)
        iy = min(max(int(np.rint((t - t0) / ds)), 0), ny - 1)
        material[i] = material_grid[iy, ix]
        albedo[i] = _bilinear_clamped(texture, s0, t0, ds, s, t)
