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
import threading  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402
from numba import njit, prange  # noqa: E402

# All flags of fastmath=True except nnan/ninf (outputs carry NaN on purpose).
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
ROWS_PER_BLOCK = 8
# numba's workqueue threading layer aborts the process when two threads launch parallel
# kernels at once: every launch holds this lock (the kernel itself releases the GIL).
KERNEL_LOCK = threading.Lock()

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


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def atan2_0_2pi(y, x):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled (float32 in and out)
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


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def atan2_array(y: npt.NDArray[np.float32], x: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:  # pragma: no cover
    """Elementwise :func:`atan2_0_2pi` (for tests): 1-D float32 in, float32 in [0, 2π) out."""
    out = np.empty(y.shape[0], np.float32)
    for i in range(y.shape[0]):
        out[i] = atan2_0_2pi(y[i], x[i])
    return out


# Row helpers: each is compiled (and vectorised by LLVM) as its own function on 1-D
# arguments; inside one big parallel body LLVM could not prove the row buffers distinct.
@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _accumulate(row, s_acc, c_acc, total, top, sn, cn):  # pragma: no cover
    for u in range(row.shape[0]):
        x = np.float32(row[u])
        s_acc[u] += x * sn
        c_acc[u] += x * cn
    for u in range(row.shape[0]):
        x = np.float32(row[u])
        total[u] += x
        top[u] = max(top[u], x)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _wrapped_row(s_acc, c_acc, mod, phw, bmin, mod_scale):  # pragma: no cover
    for u in range(s_acc.shape[0]):
        yy = -s_acc[u]
        xx = c_acc[u]
        mod[u] = mod_scale * np.sqrt(xx * xx + yy * yy)
        phw[u] = atan2_0_2pi(yy, xx)
    for u in range(s_acc.shape[0]):
        bmin[u] = min(bmin[u], mod[u])


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _unwrap_row(prev, phw, bad, ratio, cons_rad):  # pragma: no cover
    for u in range(prev.shape[0]):
        e = ratio * prev[u] - phw[u]
        # floor(e/2π + 1/2) by truncating a shifted, positive value (vectorises)
        order = np.float32(np.int32(e * _INV_TWO_PI + _ROUND_SHIFT)) - _SHIFT
        d = e - order * _TWO_PI
        bad[u] = max(bad[u], _F1 if abs(d) >= cons_rad else _F0)
        prev[u] = phw[u] + order * _TWO_PI


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _weigh_row(wsum, wphi, mod, prev, wk, scale_fine):  # pragma: no cover
    for u in range(prev.shape[0]):
        w = wk * mod[u] * mod[u]
        wsum[u] += w
        wphi[u] += w * scale_fine * prev[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _combined_row(prev, wsum, wphi):  # pragma: no cover
    for u in range(prev.shape[0]):
        prev[u] = wphi[u] / wsum[u] if wsum[u] > _F0 else _NAN


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _height_row(prev, a0, a1, b0, b1, phi0, inv_sphi, sing_rtol, den, hbuf, code):  # pragma: no cover
    for u in range(prev.shape[0]):
        pp = (prev[u] - phi0) * inv_sphi
        b1p = b1[u] * pp
        dd = b0[u] + b1p
        den[u] = dd
        code[u] = np.uint8(5) if abs(dd) <= sing_rtol * (abs(b0[u]) + abs(b1p)) else np.uint8(0)
    for u in range(prev.shape[0]):
        pp = (prev[u] - phi0) * inv_sphi
        hbuf[u] = (a0[u] + a1[u] * pp) / den[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _code_row(hbuf, code, bad, bmin, top, lo, hi, min_mod, top_code):  # pragma: no cover
    # precedence SATURATED > LOW_MODULATION > UNWRAP_INCONSISTENT > MODEL_SINGULAR > OUTSIDE_VOLUME
    for u in range(hbuf.shape[0]):
        h = hbuf[u]
        c = code[u]
        inside = (h >= lo) & (h <= hi)
        c = c if inside or c != 0 else np.uint8(4)
        c = np.uint8(3) if bad[u] > _F0 else c
        c = np.uint8(1) if bmin[u] < min_mod else c
        c = np.uint8(2) if top[u] >= top_code else c
        code[u] = c


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _select_row(out, values, code):  # pragma: no cover
    for u in range(out.shape[0]):
        out[u] = values[u] if code[u] == 0 else _NAN


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _texture_row(out, total, mod, inv_frames):  # pragma: no cover
    for u in range(out.shape[0]):
        out[u] = total[u] * inv_frames + mod[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _points_row(pts, hbuf, code, rx, ry, inv_m, offset):  # pragma: no cover
    # pts: the row's (W·3,) flat view, so the interleaved stores have a known stride
    for u in range(hbuf.shape[0]):
        t = (hbuf[u] - offset) * inv_m[u]
        t = t if code[u] == 0 else _NAN
        pts[3 * u] = t * rx[u]
        pts[3 * u + 1] = t * ry[u]
        pts[3 * u + 2] = t


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def fused_kernel(  # one call carries every table to keep the kernel fused
    frames, cos_t, sin_t, freqs, max_code, min_mod, cons_rad, combine,
    a0, a1, b0, b1, phi0, inv_sphi, lo, hi, sing_rtol, rx, ry, inv_m, offset,
    depth, points, reason, valid, modulation, texture, phase,
):  # pragma: no cover - compiled
    """Raw frames → all per-pixel outputs (see module docstring). Writes into the outputs.

    Rows are processed in blocks (``prange``), each row entirely in cache-resident
    float32 buffers: the frames and the tables are read once, the outputs written once.
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
        buf = np.empty((13, width), np.float32)
        s_acc, c_acc, total, top, phw, mod, prev = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5], buf[6]
        bmin, bad, wsum, wphi, hbuf, den = buf[7], buf[8], buf[9], buf[10], buf[11], buf[12]
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
                    _accumulate(frames[ki * n_steps + n, v], s_acc, c_acc, total, top, sin_t[n], cos_t[n])
                _wrapped_row(s_acc, c_acc, mod, phw, bmin, mod_scale)
                if ki == 0:
                    prev[:] = phw
                else:
                    _unwrap_row(prev, phw, bad, freqs[ki] / freqs[ki - 1], cons_rad)
                if combine:
                    k = freqs[ki]
                    _weigh_row(wsum, wphi, mod, prev, np.float32(n_steps) * k * k, k_max / k)
            if combine:
                _combined_row(prev, wsum, wphi)
            _height_row(prev, a0[v], a1[v], b0[v], b1[v], phi0, inv_sphi, sing_rtol, den, hbuf, code)
            _code_row(hbuf, code, bad, bmin, top, lo, hi, min_mod, top_code)
            _select_row(depth[v], hbuf, code)
            _select_row(phase[v], prev, code)
            reason[v] = code
            valid[v] = code == 0
            modulation[v] = mod
            _texture_row(texture[v], total, mod, inv_frames)
            _points_row(points[v].reshape(3 * width), hbuf, code, rx[v], ry[v], inv_m[v], offset)


NUMBA_VERSION = numba.__version__

_warm: set[str] = set()


def warmup(dtype: object = np.uint8) -> None:
    """Compile (or load from the disk cache) the kernel for ``dtype`` frames once per process."""
    dt = np.dtype(dtype)  # type: ignore[call-overload]
    if dt.name in _warm:
        return
    with KERNEL_LOCK:
        _warmup_locked(dt)


def _warmup_locked(dt: np.dtype) -> None:  # type: ignore[type-arg]
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
