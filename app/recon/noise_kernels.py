"""numba kernels of :mod:`app.recon.noise`: the set's statistics in one pass, the harmonic fit.

Serial (``nogil``): the fit reads a subsample of a few ten thousand pixels, and the live
path runs it beside the reconstruction kernel.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, error_model="numpy", cache=True)
def set_statistics(  # type: ignore[no-untyped-def]
        stack, step, n, basis, top, intensity, usable, level, phasor, resid):
    """See :func:`app.recon.noise._set_statistics` (every ``step``-th row and column)."""
    f_n = stack.shape[0]
    k_n = f_n // n
    rows, cols = intensity.shape
    n_b = basis.shape[1]
    total = np.zeros(cols, np.int64)
    lo = np.empty(cols, np.int64)
    hi = np.empty(cols, np.int64)
    proj = np.empty((n_b, cols))
    for r in range(rows):
        y = r * step
        total[:] = 0
        lo[:] = top + 1
        hi[:] = -1
        for k in range(k_n):
            proj[:] = 0.0
            before = total.copy()
            for s in range(n):
                row = stack[k * n + s, y]
                for c in range(cols):
                    v = np.int64(row[c * step])
                    total[c] += v
                    lo[c] = min(lo[c], v)
                    hi[c] = max(hi[c], v)
                for j in range(n_b):
                    b = basis[s, j]
                    for c in range(cols):
                        proj[j, c] += b * row[c * step]
            for c in range(cols):
                level[k, r, c] = (total[c] - before[c]) / n
                phasor[k, 0, r, c] = proj[0, c]
                phasor[k, 1, r, c] = proj[1, c]
                for j in range(n_b - 2):
                    resid[k, j, r, c] = proj[2 + j, c]
        for c in range(cols):
            intensity[r, c] = total[c] / f_n
            usable[r, c] = lo[c] > 0 and hi[c] < top


#: pixels per chunk of the harmonic fit: its temporaries stay in the L2 cache
#: (app.recon.noise.FIT_CHUNK)
CHUNK = 1024


@njit(nogil=True, fastmath=True, error_model="numpy", cache=True, inline="always")
def _powers(re, im, lo, hi, upow, mag):  # type: ignore[no-untyped-def]
    """mag[:hi − lo] = |z|, upow[h, 0/1, :hi − lo] = Re/Im (z/|z|)^h for pixels lo … hi − 1."""
    for p in range(hi - lo):
        r, i = re[lo + p], im[lo + p]
        mag[p] = np.sqrt(r * r + i * i)
        inv = 1.0 / mag[p] if mag[p] > 0.0 else 0.0
        upow[0, 0, p] = 1.0
        upow[0, 1, p] = 0.0
        upow[1, 0, p] = r * inv if mag[p] > 0.0 else 1.0
        upow[1, 1, p] = i * inv
    for h in range(2, upow.shape[0]):
        for p in range(hi - lo):
            a, b = upow[h - 1, 0, p], upow[h - 1, 1, p]
            upow[h, 0, p] = a * upow[1, 0, p] - b * upow[1, 1, p]
            upow[h, 1, p] = a * upow[1, 1, p] + b * upow[1, 0, p]


@njit(nogil=True, fastmath=True, error_model="numpy", cache=True, inline="always")
def _regressors(sources_j, mag, upow, x, count):  # type: ignore[no-untyped-def]
    """x[2i, :count], x[2i + 1, :count] = B cos hφ, B sin hφ for h = sources_j[i]."""
    for i in range(sources_j.shape[0]):
        h = sources_j[i]
        for p in range(count):
            x[2 * i, p] = mag[p] * upow[h, 0, p]
            x[2 * i + 1, p] = mag[p] * upow[h, 1, p]


@njit(nogil=True, fastmath=True, error_model="numpy", cache=True)
def harmonic_fit(  # type: ignore[no-untyped-def]
        level, phasor, resid, basis, moments, sources, mask, var, design, coef_out):
    """See :func:`app.recon.noise._harmonic_fit`. Per frequency two sweeps over chunks of
    :data:`CHUNK` pixels: the normal equations over the mask, then the residual and the
    noise's weights through the fitted model; each inner loop is flat and vectorises.
    ``coef_out`` (K, d, 2·S) gets the fitted (a_h, b_h) of each frequency and column."""
    k_n, d, rows, cols = resid.shape
    n = basis.shape[0]
    size = rows * cols
    n_src = sources.shape[1]
    m = 2 * n_src
    top_h = 0
    for j in range(d):
        for i in range(n_src):
            top_h = max(top_h, sources[j, i])
    weight = mask.ravel().astype(np.float64)
    flat = resid.reshape(k_n, d, size)
    out = var.ravel()
    out_a = design[0].ravel()
    out_b = design[1].ravel()
    out[:] = 0.0
    out_a[:] = 0.0
    out_b[:] = 0.0
    upow = np.empty((top_h + 2, 2, CHUNK))  # unit phasor^h, h = 0 … top_h + 1
    mag = np.empty(CHUNK)
    x = np.empty((m, CHUNK))
    alpha = np.empty(CHUNK)
    beta = np.empty(CHUNK)
    coef = np.empty((d, m))
    for k in range(k_n):
        re = phasor[k, 0].ravel()
        im = phasor[k, 1].ravel()
        lev = level[k].ravel()
        ata = np.zeros((d, m, m))
        atb = np.zeros((d, m))
        # the normal equations from every other chunk: a few shared numbers need far fewer
        # pixels than the per-pixel residual
        for lo in range(0, size, 2 * CHUNK):
            hi = min(lo + CHUNK, size)
            cnt = hi - lo
            _powers(re, im, lo, hi, upow, mag)
            for j in range(d):
                _regressors(sources[j], mag, upow, x, cnt)
                for a in range(m):
                    acc = 0.0
                    for p in range(cnt):
                        acc += weight[lo + p] * x[a, p] * flat[k, j, lo + p]
                    atb[j, a] += acc
                    for b in range(a, m):
                        acc = 0.0
                        for p in range(cnt):
                            acc += weight[lo + p] * x[a, p] * x[b, p]
                        ata[j, a, b] += acc
        for j in range(d):
            for a in range(m):
                for b in range(a):
                    ata[j, a, b] = ata[j, b, a]
                ata[j, a, a] += 1e-9 * (ata[j, a, a] + 1.0)  # an all-dark set stays solvable
            coef[j] = np.linalg.solve(ata[j], atb[j])
            coef_out[k, j] = coef[j]
        for lo in range(0, size, CHUNK):
            hi = min(lo + CHUNK, size)
            cnt = hi - lo
            _powers(re, im, lo, hi, upow, mag)
            for j in range(d):
                _regressors(sources[j], mag, upow, x, cnt)
                for p in range(cnt):
                    e = flat[k, j, lo + p]
                    for a in range(m):
                        e -= coef[j, a] * x[a, p]
                    out[lo + p] += e * e
                # the model M(C, S) = Re Σ γ_i z^h |z|^(1−h), γ_i = a_i − i·b_i, moves with
                # the samples' noise: ∂M/∂C = Re(G_z + G_z̄), ∂M/∂S = −Im(G_z − G_z̄),
                # G_z = Σ γ_i (1 + h)/2 u^(h−1), G_z̄ = Σ γ_i (1 − h)/2 u^(h+1)
                alpha[:cnt] = 0.0
                beta[:cnt] = 0.0
                for i in range(n_src):
                    h = sources[j, i]
                    ga, gb = coef[j, 2 * i], -coef[j, 2 * i + 1]
                    f1, f2 = 0.5 * (1 + h), 0.5 * (1 - h)
                    for p in range(cnt):
                        zr = f1 * (ga * upow[h - 1, 0, p] - gb * upow[h - 1, 1, p])
                        zi = f1 * (ga * upow[h - 1, 1, p] + gb * upow[h - 1, 0, p])
                        br = f2 * (ga * upow[h + 1, 0, p] - gb * upow[h + 1, 1, p])
                        bi = f2 * (ga * upow[h + 1, 1, p] + gb * upow[h + 1, 0, p])
                        alpha[p] += zr + br
                        beta[p] -= zi - bi
                # the residual's noise is Σ_n w_n ε_n, w_n = q_jn − α cos δ_n − β sin δ_n:
                # variance read²·Σ w_n² + gain·Σ w_n² I_n, Σ w_n² = 1 + (α² + β²)·N/2; the
                # second from the moments Σ_n e_u e_v I_n (e: q_j, cos δ, sin δ) of the
                # samples I_n = level + (2/N)(C cos δ_n + S sin δ_n) + Σ_j' r_j' q_j'n
                mj = moments[j]
                for p in range(cnt):
                    q = lo + p
                    u0, u1, u2 = lev[q], (2.0 / n) * re[q], (2.0 / n) * im[q]
                    m0 = mj[0, 0] * u0 + mj[0, 1] * u1 + mj[0, 2] * u2
                    m1 = mj[1, 0] * u0 + mj[1, 1] * u1 + mj[1, 2] * u2
                    m2 = mj[2, 0] * u0 + mj[2, 1] * u1 + mj[2, 2] * u2
                    m3 = mj[3, 0] * u0 + mj[3, 1] * u1 + mj[3, 2] * u2
                    m4 = mj[4, 0] * u0 + mj[4, 1] * u1 + mj[4, 2] * u2
                    m5 = mj[5, 0] * u0 + mj[5, 1] * u1 + mj[5, 2] * u2
                    for jj in range(d):
                        r = flat[k, jj, q]
                        m0 += mj[0, 3 + jj] * r
                        m1 += mj[1, 3 + jj] * r
                        m2 += mj[2, 3 + jj] * r
                        m3 += mj[3, 3 + jj] * r
                        m4 += mj[4, 3 + jj] * r
                        m5 += mj[5, 3 + jj] * r
                    al, be = alpha[p], beta[p]
                    out_a[q] += 1.0 + (al * al + be * be) * (0.5 * n)
                    out_b[q] += (m0 - 2.0 * al * m1 - 2.0 * be * m2 + al * al * m3 + be * be * m4
                                 + 2.0 * al * be * m5)
    scale = 1.0 / (k_n * d)
    for p in range(size):
        out[p] *= scale
        out_a[p] *= scale
        out_b[p] *= scale
