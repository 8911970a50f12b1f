"""Per-frame numba kernels: fringes + motion + noise + ADC, one pass over the image.

Noise: a xorshift64* generator gives 64 random bits per call, split into four 16-bit
indices of a 65536-entry table of normal quantiles (unit variance) — four exact-quantile
Gaussian deviates per draw, a real RNG whose statistics match N(0, 1) to 1/65536.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _next(state):  # noqa: ANN001, ANN202
    x = state[0]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[0] = x
    return x * np.uint64(0x2545F4914F6CDD1D)


@nb.njit(cache=True, fastmath=True, inline="always")
def _adc(mean, g, read2, maxv, z):  # noqa: ANN001, ANN202
    if mean < 0.0:
        mean = 0.0
    val = mean + math.sqrt(g * mean + read2) * z + 0.5
    if val < 0.0:
        return 0
    if val > maxv:
        return maxv
    return int(val)


@nb.njit(cache=True, fastmath=True)
def render_static(out, base, fringe, ck, sk, cosd, sind, lut, qbar, scale, amb, g, read2, maxv, table, state):  # noqa: ANN001, ANN201
    """out[i] = ADC(scale·(base·q̄ + fringe·(lut[p] − q̄)) + amb + noise), p the 8-bit pattern level.

    base, fringe, ck, sk: (N,) float32 per pixel (fringe attenuated by blur; ck/sk = cos/sin φ_k).
    scale: DN per unit of base; amb: DN of ambient light; g: DN per electron; read2: read variance DN².
    """
    n = out.shape[0]
    i = 0
    while i < n:
        r = _next(state)
        for j in range(4):
            if i >= n:
                break
            z = table[(r >> np.uint64(16 * j)) & np.uint64(0xFFFF)]
            p = 0.5 + 0.5 * (ck[i] * cosd - sk[i] * sind)
            q = lut[int(p * 255.0 + 0.5)]
            m = scale * (base[i] * qbar + fringe[i] * (q - qbar)) + amb
            out[i] = _adc(m, g, read2, maxv, z)
            i += 1


@nb.njit(cache=True, fastmath=True)
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


@nb.njit(cache=True, fastmath=True)
def mean_static(mean, base, fringe, ck, sk, cosd, sind, lut, qbar, scale, amb):  # noqa: ANN001, ANN201
    for i in range(mean.shape[0]):
        p = 0.5 + 0.5 * (ck[i] * cosd - sk[i] * sind)
        mean[i] = scale * (base[i] * qbar + fringe[i] * (lut[int(p * 255.0 + 0.5)] - qbar)) + amb


@nb.njit(cache=True, fastmath=True)
def mean_moving(mean, points, base, fringe, delta, K, alpha, a_c, gam, g_c, two_pi_k_over_w, shift,
                width_p, lut, qbar, scale, amb):  # noqa: ANN001, ANN201
    """Noise-free frame of a rigidly translated scene (translation ``delta``, mm).

    Each pixel takes the rest-pose surface sample it now sees, found by one backward step of
    the pinhole image flow (nearest sample), then the exact projector column of that sample
    moved by ``delta``. points: (H, W, 3) rest-pose points (NaN = nothing); base, fringe: (H, W).
    """
    h, w = base.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    dx, dy, dz = delta[0], delta[1], delta[2]
    for v in range(h):
        for u in range(w):
            x0, y0, z0 = points[v, u, 0], points[v, u, 1], points[v, u, 2]
            su, sv = u, v
            if z0 == z0:
                fu = fx * ((x0 + dx) / (z0 + dz) - x0 / z0)
                fv = fy * ((y0 + dy) / (z0 + dz) - y0 / z0)
                su = min(max(int(u - fu + 0.5), 0), w - 1)
                sv = min(max(int(v - fv + 0.5), 0), h - 1)
            b = base[sv, su]
            if b <= 0.0:
                mean[v, u] = amb
                continue
            X = points[sv, su, 0] + dx
            Y = points[sv, su, 1] + dy
            Z = points[sv, su, 2] + dz
            xp = (alpha[0] * X + alpha[1] * Y + alpha[2] * Z - a_c) / (gam[0] * X + gam[1] * Y + gam[2] * Z - g_c)
            if xp < -0.5 or xp > width_p - 0.5:
                mean[v, u] = amb
                continue
            p = 0.5 + 0.5 * math.cos(two_pi_k_over_w * xp + shift)
            mean[v, u] = scale * (b * qbar + fringe[sv, su] * (lut[int(p * 255.0 + 0.5)] - qbar)) + amb
