"""Per-frame numba kernels: fringes + motion + noise + ADC, one pass over the image.

Noise: a xorshift64* generator gives 64 random bits per call, split into four 16-bit
indices of a 65536-entry table of normal quantiles (unit variance) — four exact-quantile
Gaussian deviates per draw, a real RNG whose statistics match N(0, 1) to 1/65536.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

# fast-math without the no-NaN/no-Inf assumptions (the kernels test for NaN).
FAST = {"contract", "arcp", "reassoc", "nsz", "afn"}


@nb.njit(cache=True, inline="always")
def _next(state):  # noqa: ANN001, ANN202
    x = state[0]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[0] = x
    return x * np.uint64(0x2545F4914F6CDD1D)


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _adc(mean, g, read2, maxv, z):  # noqa: ANN001, ANN202
    if mean < 0.0:
        mean = 0.0
    val = mean + math.sqrt(g * mean + read2) * z + 0.5
    if val < 0.0:
        return 0
    if val > maxv:
        return maxv
    return int(val)


@nb.njit(cache=True, nogil=True, fastmath=FAST)
def add_noise(out, mean, g, read2, maxv, table, state):  # noqa: ANN001, ANN201
    """out[i] = ADC(mean[i] + noise) for a precomputed noise-free mean (DN)."""
    n = out.shape[0]
    i = 0
    while i < n:
        r = _next(state)
        for j in range(4):
            if i >= n:
                break
            out[i] = _adc(mean[i], g, read2, maxv, table[(r >> np.uint64(16 * j)) & np.uint64(0xFFFF)])
            i += 1


@nb.njit(cache=True, nogil=True, fastmath=FAST)
def mean_static(mean, base, fringe, ck, sk, cosd, sind, lut, qbar, scale, amb):  # noqa: ANN001, ANN201
    for i in range(mean.shape[0]):
        p = 0.5 + 0.5 * (ck[i] * cosd - sk[i] * sind)
        mean[i] = scale * (base[i] * qbar + fringe[i] * (lut[int(p * 255.0 + 0.5)] - qbar)) + amb


@nb.njit(cache=True, nogil=True, fastmath=FAST)
def moving_frame(out, noisy, nd, base, fringe, block_flow, block, n_add, d_add, k_over_w, shift_frac,
                 width_p, qtab, qbar, scale, amb, g, read2, maxv, table, state):  # noqa: ANN001, ANN201
    """A frame of a rigidly translated scene: the noise-free mean (``noisy`` False, ``out``
    float32) or the noisy, quantised frame (``noisy`` True, ``out`` uint8/uint16), in one pass.

    Each ``block``×``block`` tile takes the rest-pose samples it now sees through one backward
    step of its (integer, per-tile) image flow ``block_flow`` (tiles_y, tiles_x, 2); the
    projector column of each sample moved by δ is exact: x_p = (N0 + α·δ)/(D0 + γ·δ) with
    nd = (N0, D0) per pixel ((H, W, 2) float32) and n_add = α·δ, d_add = γ·δ.
    base, fringe: (H, W) float32 (0 where unlit); qtab: projector output over one period.
    """
    h, w = base.shape
    nq = qtab.shape[0]
    ty, tx = block_flow.shape[0], block_flow.shape[1]
    r = np.uint64(0)
    j = 4
    for by in range(ty):
        for bx in range(tx):
            fu = block_flow[by, bx, 0]
            fv = block_flow[by, bx, 1]
            for v in range(by * block, min((by + 1) * block, h)):
                sv = min(max(v - fv, 0), h - 1)
                for u in range(bx * block, min((bx + 1) * block, w)):
                    su = min(max(u - fu, 0), w - 1)
                    b = base[sv, su]
                    m = amb
                    if b > 0.0:
                        xp = (nd[sv, su, 0] + n_add) / (nd[sv, su, 1] + d_add)
                        if -0.5 <= xp <= width_p - 0.5:
                            f = xp * k_over_w + shift_frac + 1.0
                            f -= int(f)
                            q = qtab[min(int(f * nq), nq - 1)]
                            m = scale * (b * qbar + fringe[sv, su] * (q - qbar)) + amb
                    if noisy:
                        if j == 4:
                            r = _next(state)
                            j = 0
                        z = table[(r >> np.uint64(16 * j)) & np.uint64(0xFFFF)]
                        j += 1
                        out[v, u] = _adc(m, g, read2, maxv, z)
                    else:
                        out[v, u] = m


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _capsule_t(rx, ry, rz, p0, a_hat, length, radius):  # noqa: ANN001, ANN202
    """Ray (from the origin, direction r) against a capsule; returns (t, nx, ny, nz) or t = inf."""
    best = math.inf
    bx = by = bz = 0.0
    ox, oy, oz = -p0[0], -p0[1], -p0[2]
    da = rx * a_hat[0] + ry * a_hat[1] + rz * a_hat[2]
    oa = ox * a_hat[0] + oy * a_hat[1] + oz * a_hat[2]
    dpx, dpy, dpz = rx - da * a_hat[0], ry - da * a_hat[1], rz - da * a_hat[2]
    opx, opy, opz = ox - oa * a_hat[0], oy - oa * a_hat[1], oz - oa * a_hat[2]
    a = dpx * dpx + dpy * dpy + dpz * dpz
    b = 2.0 * (dpx * opx + dpy * opy + dpz * opz)
    c = opx * opx + opy * opy + opz * opz - radius * radius
    disc = b * b - 4 * a * c
    if disc >= 0.0 and a > 0.0:
        t = (-b - math.sqrt(disc)) / (2 * a)
        ax = oa + t * da
        if t > 0.0 and 0.0 <= ax <= length:
            best = t
            bx, by, bz = opx + t * dpx, opy + t * dpy, opz + t * dpz
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


@nb.njit(cache=True, nogil=True, fastmath=FAST)
def draw_tool(mean, rays, points, dz, v0, spans, p0, a_hat, length, radius, refl, ks, shin,
              proj_c, alpha, a_c, gam, g_c, width_p, height_p, proj_fy, proj_cy, two_pi_k_over_w, shift,
              atten, lut, qbar, scale, amb):  # noqa: ANN001, ANN201
    """Overwrite ``mean`` where the capsule tool is in front of the scene.

    spans: (n, 2) int first/last column to test in rows v0 .. v0 + n − 1 (the tool's image).
    """
    for r in range(spans.shape[0]):
        v = v0 + r
        for u in range(spans[r, 0], spans[r, 1] + 1):
            rx, ry, rz = rays[v, u, 0], rays[v, u, 1], rays[v, u, 2]
            t, nx, ny, nz = _capsule_t(rx, ry, rz, p0, a_hat, length, radius)
            zs = points[v, u, 2] + dz
            if t == math.inf or (zs == zs and t * rz >= zs):
                continue
            X, Y, Z = t * rx, t * ry, t * rz
            lx, ly, lz = proj_c[0] - X, proj_c[1] - Y, proj_c[2] - Z
            d = math.sqrt(lx * lx + ly * ly + lz * lz)
            lx, ly, lz = lx / d, ly / d, lz / d
            cos_i = nx * lx + ny * ly + nz * lz
            xp = (alpha[0] * X + alpha[1] * Y + alpha[2] * Z - a_c) / (gam[0] * X + gam[1] * Y + gam[2] * Z - g_c)
            yp = proj_fy * (0.0) + proj_cy  # rows: checked loosely below via the projector frame
            if cos_i <= 0.0 or xp < -0.5 or xp > width_p - 0.5 or yp < -0.5 or yp > height_p:
                mean[v, u] = amb
                continue
            nv = math.sqrt(X * X + Y * Y + Z * Z)
            hx, hy, hz = lx - X / nv, ly - Y / nv, lz - Z / nv
            hn = math.sqrt(hx * hx + hy * hy + hz * hz)
            cos_h = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
            base = (refl * cos_i + 0.05 * ks * cos_h**shin) / (d * d)
            p = 0.5 + 0.5 * math.cos(two_pi_k_over_w * xp + shift)
            mean[v, u] = scale * (base * qbar + atten * base * (lut[int(p * 255.0 + 0.5)] - qbar)) + amb
