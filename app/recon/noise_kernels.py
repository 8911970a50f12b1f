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
    """x[2i, :count], x[2i + 1, :count] = B cos hφ, B sin hφ for h = sources_j[i]: the fit's
    regressors at the median level (those of t and t² are these times t, t²)."""
    for i in range(sources_j.shape[0]):
        h = sources_j[i]
        for p in range(count):
            x[2 * i, p] = mag[p] * upow[h, 0, p]
            x[2 * i + 1, p] = mag[p] * upow[h, 1, p]


@njit(nogil=True, fastmath=True, error_model="numpy", cache=True)
def harmonic_fit(  # type: ignore[no-untyped-def]
        level, phasor, resid, basis, moments, sources, centre, ridge, mask, var, design,
        coef_out):
    """See :func:`app.recon.noise._harmonic_fit`. Per frequency two sweeps over chunks of
    :data:`CHUNK` pixels: the normal equations over the mask, then the residual and the
    noise's weights through the fitted model; each inner loop is flat and vectorises.
    ``centre`` (K,) holds each frequency's median level Ã over the mask, ``ridge`` the
    relative ridge ρ on the normal equations' diagonal; ``coef_out`` (K, d, 6·S) gets the
    fitted coefficients of each frequency and column: of :func:`_regressors`' rows x_i, then
    of x_i·t, then of x_i·t² (t = A/Ã − 1)."""
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
    x = np.empty((m0, CHUNK))
    wt = np.empty((5, CHUNK))  # mask weight × t^q
    xx = np.empty(CHUNK)
    res = np.empty(CHUNK)
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
        sums = np.zeros((d, m0, m0, 5))
        # the normal equations from every other chunk: a few shared numbers need far fewer
        # pixels than the per-pixel residual
        for lo in range(0, size, 2 * CHUNK):
            hi = min(lo + CHUNK, size)
            cnt = hi - lo
            _powers(re, im, lo, hi, upow, mag)
            # the regressors are x_i·t^s (x_i at the median level, s = 0, 1, 2): the normal
            # equations need Σ w x_i x_i' t^q, q = 0 … 4, and Σ w x_i r t^s only
            for p in range(cnt):
                t = lev[lo + p] * inv_a - 1.0
                wt[0, p] = weight[lo + p]
                for q in range(1, 5):
                    wt[q, p] = wt[q - 1, p] * t
            for j in range(d):
                _regressors(sources[j], mag, upow, x, cnt)
                for a in range(m0):
                    for q in range(3):
                        acc = 0.0
                        for p in range(cnt):
                            acc += wt[q, p] * x[a, p] * flat[k, j, lo + p]
                        atb[j, q * m0 + a] += acc
                    for b in range(a, m0):
                        for p in range(cnt):
                            xx[p] = x[a, p] * x[b, p]
                        for q in range(5):
                            acc = 0.0
                            for p in range(cnt):
                                acc += wt[q, p] * xx[p]
                            sums[j, a, b, q] += acc
        for j in range(d):
            for a in range(m0):
                for b in range(a, m0):
                    for s_a in range(3):
                        for s_b in range(3):
                            # row (s_a, a), column (s_b, b) and its mirror (s_b, b), (s_a, a)
                            v = sums[j, a, b, s_a + s_b]
                            ata[j, s_a * m0 + a, s_b * m0 + b] = v
                            ata[j, s_b * m0 + b, s_a * m0 + a] = v
        for j in range(d):
            for a in range(m):
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
                for p in range(cnt):
                    res[p] = flat[k, j, lo + p]
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
                        # the model's value: B (a cos hφ + b sin hφ), b = −gb
                        res[p] -= mag[p] * (ga * upow[h, 0, p] - gb * upow[h, 1, p])
                for p in range(cnt):
                    out[lo + p] += res[p] * res[p]
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
