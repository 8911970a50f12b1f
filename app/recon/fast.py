"""The fast path: one fused, parallel numba kernel from raw frames to depth and points.

Per block of rows (``prange``) the kernel keeps row-long float32 buffers so that every
inner loop runs along a contiguous row and LLVM can vectorise it: accumulate Σ I sinδ,
Σ I cosδ, Σ I and max I per frequency; a branch-free polynomial atan2; the hierarchical
unwrapping with its consistency test; then Eq. (5) from precomputed per-pixel tables,
the ray intersection and the reason code. Frames are read once, outputs written once:
the kernel is memory bound.

Semantics are those of the numpy oracle (``phase``/``unwrap``/``model``/``points``);
only the arithmetic is float32. ``fastmath`` excludes ``nnan``/``ninf`` because NaN
marks invalid pixels. The JIT result is cached on disk (``cache=True``).
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")  # spinning OpenMP threads: 8× slower on 2 cores

import math  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402
from numba import njit, prange  # noqa: E402

# All flags of fastmath=True except nnan/ninf (outputs carry NaN on purpose).
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
ROWS_PER_BLOCK = 8

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_HALF = np.float32(0.5)
_PI = np.float32(math.pi)
_HALF_PI = np.float32(0.5 * math.pi)
_TWO_PI = np.float32(2.0 * math.pi)
_INV_TWO_PI = np.float32(1.0 / (2.0 * math.pi))
_TINY = np.float32(1e-30)
_NAN = np.float32(np.nan)
_INF = np.float32(np.inf)
_SHIFT = np.float32(64.0)  # orders stay far above -64
_ROUND_SHIFT = np.float32(64.5)
# atan(a) ≈ a·P(a²) on [0, 1]: weighted least-squares minimax fit, max error 3.7e-8 rad
# in float64 (1.2e-7 evaluated in float32; see tests/recon/test_fast.py).
_A0 = np.float32(0.9999993356608105)
_A1 = np.float32(-0.33329860955265084)
_A2 = np.float32(0.1994656676652332)
_A3 = np.float32(-0.13908632720069006)
_A4 = np.float32(0.09642201479625472)
_A5 = np.float32(-0.05591234645397164)
_A6 = np.float32(0.021862953185210254)
_A7 = np.float32(-0.004054562176639915)


@njit(fastmath=FASTMATH, cache=True)
def atan2_0_2pi(y: float, x: float) -> float:  # pragma: no cover - compiled
    """Branch-free float32 atan2 mapped to [0, 2π)."""
    ax = abs(x)
    ay = abs(y)
    mn = min(ax, ay)
    mx = max(max(ax, ay), _TINY)
    a = mn / mx
    s = a * a
    p = ((((((_A7 * s + _A6) * s + _A5) * s + _A4) * s + _A3) * s + _A2) * s + _A1) * s + _A0
    r = p * a
    r = _HALF_PI - r if ay > ax else r
    r = _PI - r if x < _F0 else r
    r = _TWO_PI - r if y < _F0 else r
    return _F0 if r >= _TWO_PI else r


@njit(fastmath=FASTMATH, cache=True)
def atan2_array(y: npt.NDArray[np.float32], x: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:  # pragma: no cover
    """Elementwise :func:`atan2_0_2pi` (for tests): 1-D float32 in, float32 in [0, 2π) out."""
    out = np.empty(y.shape[0], np.float32)
    for i in range(y.shape[0]):
        out[i] = atan2_0_2pi(y[i], x[i])
    return out


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def fused_kernel(  # one call carries every table to keep the kernel fused
    frames, cos_t, sin_t, freqs, max_code, min_mod, cons_rad, combine,
    a0, a1, b0, b1, phi0, inv_sphi, lo, hi, sing_rtol, rx, ry, inv_m, offset,
    depth, points, reason, valid, modulation, texture, phase,
):  # pragma: no cover - compiled
    """Raw frames → all per-pixel outputs (see module docstring). Writes into the outputs.

    Each inner loop touches few arrays so that LLVM's runtime alias checks stay below
    its limit and the loop vectorises; numba cannot tell LLVM that arrays do not alias.
    """
    n_frames, height, width = frames.shape
    n_steps = cos_t.shape[0]
    n_freq = freqs.shape[0]
    k_max = freqs[n_freq - 1]
    mod_scale = np.float32(2.0) / np.float32(n_steps)
    inv_frames = _F1 / np.float32(n_frames)
    top_code = np.float32(max_code)
    n_blocks = (height + ROWS_PER_BLOCK - 1) // ROWS_PER_BLOCK
    for blk in prange(n_blocks):
        s_acc = np.empty(width, np.float32)
        c_acc = np.empty(width, np.float32)
        total = np.empty(width, np.float32)
        top = np.empty(width, np.float32)
        phw = np.empty(width, np.float32)
        mod = np.empty(width, np.float32)
        prev = np.empty(width, np.float32)
        bmin = np.empty(width, np.float32)
        bad = np.empty(width, np.float32)
        wsum = np.empty(width, np.float32)
        wphi = np.empty(width, np.float32)
        hbuf = np.empty(width, np.float32)
        den = np.empty(width, np.float32)
        code = np.empty(width, np.uint8)
        for v in range(blk * ROWS_PER_BLOCK, min(height, (blk + 1) * ROWS_PER_BLOCK)):
            total[:] = _F0
            top[:] = _F0
            bmin[:] = _INF
            bad[:] = _F0
            wsum[:] = _F0
            wphi[:] = _F0
            for ki in range(n_freq):
                s_acc[:] = _F0
                c_acc[:] = _F0
                for n in range(n_steps):
                    row = frames[ki * n_steps + n, v]
                    cn = cos_t[n]
                    sn = sin_t[n]
                    for u in range(width):
                        x = np.float32(row[u])
                        s_acc[u] += x * sn
                        c_acc[u] += x * cn
                    for u in range(width):
                        x = np.float32(row[u])
                        total[u] += x
                        top[u] = max(top[u], x)
                for u in range(width):
                    yy = -s_acc[u]
                    xx = c_acc[u]
                    mod[u] = mod_scale * np.sqrt(xx * xx + yy * yy)
                    phw[u] = atan2_0_2pi(yy, xx)
                for u in range(width):
                    bmin[u] = min(bmin[u], mod[u])
                if ki == 0:
                    for u in range(width):
                        prev[u] = phw[u]
                else:
                    ratio = freqs[ki] / freqs[ki - 1]
                    for u in range(width):
                        e = ratio * prev[u] - phw[u]
                        # floor(e/2π + 1/2) by truncation of a shifted positive value
                        order = np.float32(np.int32(e * _INV_TWO_PI + _ROUND_SHIFT)) - _SHIFT
                        d = e - order * _TWO_PI
                        bad[u] = max(bad[u], _F1 if abs(d) >= cons_rad else _F0)
                        prev[u] = phw[u] + order * _TWO_PI
                if combine:
                    k = freqs[ki]
                    wk = np.float32(n_steps) * k * k
                    scale_fine = k_max / k
                    for u in range(width):
                        w = wk * mod[u] * mod[u]
                        wsum[u] += w
                        wphi[u] += w * scale_fine * prev[u]
            if combine:
                for u in range(width):
                    prev[u] = wphi[u] / wsum[u] if wsum[u] > _F0 else _NAN
            rb0 = b0[v]
            rb1 = b1[v]
            for u in range(width):
                pp = (prev[u] - phi0) * inv_sphi
                b1p = rb1[u] * pp
                dd = rb0[u] + b1p
                den[u] = dd
                code[u] = np.uint8(5) if abs(dd) <= sing_rtol * (abs(rb0[u]) + abs(b1p)) else np.uint8(0)
            ra0 = a0[v]
            ra1 = a1[v]
            for u in range(width):
                pp = (prev[u] - phi0) * inv_sphi
                hbuf[u] = (ra0[u] + ra1[u] * pp) / den[u]
            for u in range(width):
                h = hbuf[u]
                c = code[u]
                c = c if (h >= lo and h <= hi) or c != 0 else np.uint8(4)
                c = np.uint8(3) if bad[u] > _F0 else c
                c = np.uint8(1) if bmin[u] < min_mod else c
                c = np.uint8(2) if top[u] >= top_code else c
                code[u] = c
            rdepth = depth[v]
            for u in range(width):
                rdepth[u] = hbuf[u] if code[u] == 0 else _NAN
            rphase = phase[v]
            for u in range(width):
                rphase[u] = prev[u] if code[u] == 0 else _NAN
            rreason = reason[v]
            for u in range(width):
                rreason[u] = code[u]
            rvalid = valid[v]
            for u in range(width):
                rvalid[u] = code[u] == 0
            rmod = modulation[v]
            for u in range(width):
                rmod[u] = mod[u]
            rtex = texture[v]
            for u in range(width):
                rtex[u] = total[u] * inv_frames + mod[u]
            rpts = points[v]
            rrx = rx[v]
            rry = ry[v]
            rinv = inv_m[v]
            for u in range(width):
                ok = code[u] == 0
                t = (hbuf[u] - offset) * rinv[u] if ok else _NAN
                rpts[u, 0] = t * rrx[u]
                rpts[u, 1] = t * rry[u]
                rpts[u, 2] = t


NUMBA_VERSION = numba.__version__

_warm: set[str] = set()


def warmup(dtype: object = np.uint8) -> None:
    """Compile (or load from the disk cache) the kernel for ``dtype`` frames once per process."""
    dt = np.dtype(dtype)  # type: ignore[call-overload]
    if dt.name in _warm:
        return
    f32 = np.zeros((2, 3), np.float32)
    frames = np.zeros((3, 2, 3), dt)
    trig = np.ones(3, np.float32)
    fused_kernel(
        frames, trig, trig, np.ones(1, np.float32), np.int32(1), np.float32(0), np.float32(1), False,
        f32, f32, f32, f32, np.float32(0), np.float32(1), np.float32(0), np.float32(1),
        np.float32(1e-5), f32, f32, f32, np.float32(0),
        np.empty((2, 3), np.float32), np.empty((2, 3, 3), np.float32), np.empty((2, 3), np.uint8),
        np.empty((2, 3), np.bool_), np.empty((2, 3), np.float32), np.empty((2, 3), np.float32),
        np.empty((2, 3), np.float32),
    )
    _warm.add(dt.name)
