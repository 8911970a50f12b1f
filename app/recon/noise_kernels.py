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
def _regressors(sources_j, mag, upow, t_level, x, count):  # type: ignore[no-untyped-def]
    """x[2i], x[2i + 1] = B cos hφ, B sin hφ for h = sources_j[i] (rows 0 … 2S − 1), then the
    same times t (rows 2S … 4S − 1) and times t² (rows 4S … 6S − 1), over :count."""
    m0 = 2 * sources_j.shape[0]
    for i in range(sources_j.shape[0]):
        h = sources_j[i]
        for p in range(count):
            c = mag[p] * upow[h, 0, p]
            s = mag[p] * upow[h, 1, p]
            t = t_level[p]
            x[2 * i, p] = c
            x[2 * i + 1, p] = s
            x[m0 + 2 * i, p] = c * t
            x[m0 + 2 * i + 1, p] = s * t
            x[2 * m0 + 2 * i, p] = c * t * t
            x[2 * m0 + 2 * i + 1, p] = s * t * t


@njit(nogil=True, fastmath=True, error_model="numpy", cache=True)
def harmonic_fit(  # type: ignore[no-untyped-def]
        level, phasor, resid, basis, moments, sources, centre, ridge, mask, var, design,
        coef_out):
    """See :func:`app.recon.noise._harmonic_fit`. Per frequency two sweeps over chunks of
    :data:`CHUNK` pixels: the normal equations over the mask, then the residual and the
    noise's weights through the fitted model; each inner loop is flat and vectorises.
    ``centre`` (K,) holds each frequency's median level Ã over the mask, ``ridge`` the
    relative ridge ρ on the normal equations' diagonal; ``coef_out`` (K, d, 6·S) gets the
    fitted coefficients of each frequency and column in the order of
    :func:`_regressors`' rows."""
    k_n, d, rows, cols = resid.shape
    n = basis.shape[0]
    size = rows * cols
    n_src = sources.shape[1]
    m0 = 2 * n_src
    m = 3 * m0
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
    t_level = np.empty(CHUNK)
    x = np.empty((m, CHUNK))
    alpha = np.empty(CHUNK)
    beta = np.empty(CHUNK)
    eps = np.empty(CHUNK)
    coef = np.empty((d, m))
    for k in range(k_n):
        re = phasor[k, 0].ravel()
        im = phasor[k, 1].ravel()
        lev = level[k].ravel()
        inv_a = 1.0 / centre[k]
        ata = np.zeros((d, m, m))
        atb = np.zeros((d, m))
        # the normal equations from every other chunk: a few shared numbers need far fewer
        # pixels than the per-pixel residual
        for lo in range(0, size, 2 * CHUNK):
            hi = min(lo + CHUNK, size)
            cnt = hi - lo
            _powers(re, im, lo, hi, upow, mag)
            for p in range(cnt):
                t_level[p] = lev[lo + p] * inv_a - 1.0
            for j in range(d):
                _regressors(sources[j], mag, upow, t_level, x, cnt)
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
                ata[j, a, a] += ridge * (ata[j, a, a] + 1.0)
            coef[j] = np.linalg.solve(ata[j], atb[j])
            coef_out[k, j] = coef[j]
        for lo in range(0, size, CHUNK):
            hi = min(lo + CHUNK, size)
            cnt = hi - lo
            _powers(re, im, lo, hi, upow, mag)
            for p in range(cnt):
                t_level[p] = lev[lo + p] * inv_a - 1.0
            for j in range(d):
                _regressors(sources[j], mag, upow, t_level, x, cnt)
                for p in range(cnt):
                    e = flat[k, j, lo + p]
                    for a in range(m):
                        e -= coef[j, a] * x[a, p]
                    out[lo + p] += e * e
                # the model M(C, S, A) = Re Σ γ_i(A) z^h |z|^(1−h), γ_i = γ_i0 + γ_i1·t +
                # γ_i2·t² (γ = a − i·b; t = A/Ã − 1) moves with the samples' noise:
                # ∂M/∂C = Re(G_z + G_z̄), ∂M/∂S = −Im(G_z − G_z̄), G_z = Σ γ_i (1 + h)/2 u^(h−1),
                # G_z̄ = Σ γ_i (1 − h)/2 u^(h+1), and ∂M/∂A = Re Σ (γ_i1 + 2γ_i2·t) u^h |z| / Ã
                alpha[:cnt] = 0.0
                beta[:cnt] = 0.0
                eps[:cnt] = 0.0
                for i in range(n_src):
                    h = sources[j, i]
                    a0, b0 = coef[j, 2 * i], -coef[j, 2 * i + 1]
                    a1, b1 = coef[j, m0 + 2 * i], -coef[j, m0 + 2 * i + 1]
                    a2, b2 = coef[j, 2 * m0 + 2 * i], -coef[j, 2 * m0 + 2 * i + 1]
                    f1, f2 = 0.5 * (1 + h), 0.5 * (1 - h)
                    for p in range(cnt):
                        t = t_level[p]
                        ga = a0 + (a1 + a2 * t) * t
                        gb = b0 + (b1 + b2 * t) * t
                        zr = f1 * (ga * upow[h - 1, 0, p] - gb * upow[h - 1, 1, p])
                        zi = f1 * (ga * upow[h - 1, 1, p] + gb * upow[h - 1, 0, p])
                        br = f2 * (ga * upow[h + 1, 0, p] - gb * upow[h + 1, 1, p])
                        bi = f2 * (ga * upow[h + 1, 1, p] + gb * upow[h + 1, 0, p])
                        alpha[p] += zr + br
                        beta[p] -= zi - bi
                        da, db = a1 + 2.0 * a2 * t, b1 + 2.0 * b2 * t
                        eps[p] += (da * upow[h, 0, p] - db * upow[h, 1, p]) * mag[p] * inv_a
                # the residual's noise is Σ_n w_n ε_n, w_n = q_jn − α cos δ_n − β sin δ_n
                # − ε/N: variance read²·Σ w_n² + gain·Σ w_n² I_n, Σ w_n² = 1 + (α² + β²)·N/2
                # + ε²/N; the second from the moments Σ_n e_u e_v I_n (e: q_j, cos δ, sin δ)
                # of the samples I_n = level + (2/N)(C cos δ_n + S sin δ_n) + Σ_j' r_j' q_j'n,
                # and for the ε terms Σ_n I_n = N·A, Σ q_jn I_n = r_j, Σ cos δ_n I_n = C, …
                mj = moments[j]
                for p in range(cnt):
                    q = lo + p
                    u0, u1, u2 = lev[q], (2.0 / n) * re[q], (2.0 / n) * im[q]
                    m0_ = mj[0, 0] * u0 + mj[0, 1] * u1 + mj[0, 2] * u2
                    m1 = mj[1, 0] * u0 + mj[1, 1] * u1 + mj[1, 2] * u2
                    m2 = mj[2, 0] * u0 + mj[2, 1] * u1 + mj[2, 2] * u2
                    m3 = mj[3, 0] * u0 + mj[3, 1] * u1 + mj[3, 2] * u2
                    m4 = mj[4, 0] * u0 + mj[4, 1] * u1 + mj[4, 2] * u2
                    m5 = mj[5, 0] * u0 + mj[5, 1] * u1 + mj[5, 2] * u2
                    for jj in range(d):
                        r = flat[k, jj, q]
                        m0_ += mj[0, 3 + jj] * r
                        m1 += mj[1, 3 + jj] * r
                        m2 += mj[2, 3 + jj] * r
                        m3 += mj[3, 3 + jj] * r
                        m4 += mj[4, 3 + jj] * r
                        m5 += mj[5, 3 + jj] * r
                    al, be, ep = alpha[p], beta[p], eps[p]
                    out_a[q] += 1.0 + (al * al + be * be) * (0.5 * n) + ep * ep / n
                    out_b[q] += (m0_ - 2.0 * al * m1 - 2.0 * be * m2 + al * al * m3
                                 + be * be * m4 + 2.0 * al * be * m5
                                 + ep * (ep * lev[q] - 2.0 * flat[k, j, q] + 2.0 * al * re[q]
                                         + 2.0 * be * im[q]) / n)
    scale = 1.0 / (k_n * d)
    for p in range(size):
        out[p] *= scale
        out_a[p] *= scale
        out_b[p] *= scale
