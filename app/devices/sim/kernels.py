"""Per-frame numba kernels: fringes + motion + noise + ADC, one pass over the image.

Noise: a xorshift64* generator gives 64 random bits per call, split into four 16-bit
indices of a 65536-entry table of normal quantiles (unit variance) — four exact-quantile
Gaussian deviates per draw, a real RNG whose statistics match N(0, 1) to 1/65536.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
I32 = npt.NDArray[np.int32]
I64 = npt.NDArray[np.int64]
U64 = npt.NDArray[np.uint64]
DN = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]  # a noisy frame: 8 or 12 bits

# fast-math without the no-NaN/no-Inf assumptions (the kernels test for NaN).
FAST = {"contract", "arcp", "reassoc", "nsz", "afn"}


@nb.njit(cache=True, inline="always")
def _next(state: U64) -> np.uint64:
    x: np.uint64 = state[0]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[0] = x
    return x * np.uint64(0x2545F4914F6CDD1D)


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _adc(mean: float, g: float, read2: float, maxv: int, z: float) -> int:
    """Quantised DN of a pixel of noise-free mean ``mean`` (DN) and unit normal deviate ``z``
    (shot + read noise, clipped to 0 .. maxv; branch-free so that row loops vectorise)."""
    mean = max(mean, 0.0)
    val = mean + math.sqrt(g * mean + read2) * z + 0.5
    return int(min(max(val, 0.0), maxv))


@nb.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def add_noise(out: DN, mean: F32, g: float, read2: float, maxv: int, table: F32,
              state: U64) -> None:
    """out[i] = ADC(mean[i] + noise) for a precomputed noise-free mean (DN)."""
    n = out.shape[0]
    i = 0
    while i < n:
        r = _next(state)
        for j in range(4):
            if i >= n:
                break
            out[i] = _adc(mean[i], g, read2, maxv,
                          table[(r >> np.uint64(16 * j)) & np.uint64(0xFFFF)])
            i += 1


@nb.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def mean_static(mean: F32, base: F32, fringe: F32, ck: F32, sk: F32, cosd: float, sind: float,
                lut: F32, qbar: float, scale: float, amb: float) -> None:
    for i in range(mean.shape[0]):
        p = 0.5 + 0.5 * (ck[i] * cosd - sk[i] * sind)
        mean[i] = scale * (base[i] * qbar + fringe[i] * (lut[int(p * 255.0 + 0.5)] - qbar)) + amb


@nb.njit(cache=True, fastmath=FAST, error_model="numpy", inline="always")
def _fringe_index(n0: float, d0: float, b: float, n_add: float, d_add: float, k_over_w: float,
                  shift_frac: float, width_p: float, nq: int) -> int:
    """Index into the (nq,) projector table of a rest-pose sample (N0, D0, base b) moved by δ
    (see moving_frame); −1 where it is unlit (b = 0 or off the pattern). Branch-free: vectorises."""
    xp = (n0 + n_add) / (d0 + d_add)
    lit = b > 0.0 and -0.5 <= xp <= width_p - 0.5
    xp = xp if lit else 0.0  # a valid table index off the pattern (xp may be NaN there)
    f = xp * k_over_w + shift_frac + 1.0
    f -= int(f)
    k = min(int(f * nq), nq - 1)
    return k if lit else -1


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _index_run(kk: I32, u0: int, u1: int, s0: int, n0_row: F32, d0_row: F32, base_row: F32,
               n_add: float, d_add: float, k_over_w: float, shift_frac: float, width_p: float,
               nq: int) -> None:
    """kk[u0 .. u1 − 1] = table indices of the contiguous rest-pose samples
    s0 .. s0 + u1 − u0 − 1."""
    for i in range(u1 - u0):
        kk[u0 + i] = _fringe_index(n0_row[s0 + i], d0_row[s0 + i], base_row[s0 + i], n_add, d_add,
                                   k_over_w, shift_frac, width_p, nq)


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _shade(q: float, b: float, fr: float, qbar: float, scale: float, amb: float) -> float:
    """DN of a sample of base b and fringe part fr lit by projector output q
    (NaN: unlit → ambient)."""
    m = scale * (b * qbar + fr * (q - qbar)) + amb
    return m if q == q else amb


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _shade_run(row: F32, qv: F32, u0: int, u1: int, s0: int, base_row: F32, fringe_row: F32,
               qbar: float, scale: float, amb: float) -> None:
    """row[u] = DN of the rest-pose sample s0 + u − u0 lit by projector
    output qv[u] (NaN: unlit)."""
    for i in range(u1 - u0):
        row[u0 + i] = _shade(qv[u0 + i], base_row[s0 + i], fringe_row[s0 + i], qbar, scale, amb)


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _flow_run(block_flow: I64, by: int, bx: int, block: int, w: int
              ) -> tuple[int, int, int, int, int, int, int]:
    """The run of tiles bx .. e − 1 of tile row ``by`` sharing tile bx's flow (fu, fv): returns
    (e, fu, fv, u0, u1, a, b) with columns u0 .. u1 − 1, of which a .. b − 1 have their
    rest-pose source u − fu inside the image (the others clamp to column 0 or W − 1)."""
    tx = block_flow.shape[1]
    fu, fv = block_flow[by, bx, 0], block_flow[by, bx, 1]
    e = bx + 1
    while e < tx and block_flow[by, e, 0] == fu and block_flow[by, e, 1] == fv:
        e += 1
    u0, u1 = bx * block, min(e * block, w)
    a = min(max(u0, fu), u1)
    return e, fu, fv, u0, u1, a, max(min(u1, w + fu), a)


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _scene_row(row: F32, kk: I32, qv: F32, v: int, nd: F32, base: F32, fringe: F32,
               block_flow: I64, block: int, n_add: float, d_add: float, k_over_w: float,
               shift_frac: float, width_p: float, qtab: F32, qbar: float, scale: float,
               amb: float) -> None:
    """Noise-free row ``v`` (W,) float32 DN of the moved scene (see moving_frame) into ``row``.

    Neighbouring tiles mostly share their flow, so each run of equal flow reads a contiguous
    stretch of one rest-pose row. Three passes keep the arithmetic vectorised: table indices
    (kk, (W,) int32), the table look-up (qv, (W,) float32; a gather, scalar), the shading.
    """
    h, w = base.shape
    by = v // block
    nq = qtab.shape[0]
    bx = 0
    while bx < block_flow.shape[1]:
        bx2, fu, fv, u0, u1, a, b = _flow_run(block_flow, by, bx, block, w)
        sv = min(max(v - fv, 0), h - 1)
        n0_row, d0_row, base_row = nd[0, sv], nd[1, sv], base[sv]
        for u in range(u0, a):
            kk[u] = _fringe_index(n0_row[0], d0_row[0], base_row[0], n_add, d_add, k_over_w,
                                  shift_frac, width_p, nq)
        _index_run(kk, a, b, a - fu, n0_row, d0_row, base_row, n_add, d_add, k_over_w, shift_frac,
                   width_p, nq)
        for u in range(b, u1):
            kk[u] = _fringe_index(n0_row[w - 1], d0_row[w - 1], base_row[w - 1], n_add, d_add,
                                  k_over_w, shift_frac, width_p, nq)
        bx = bx2
    for u in range(w):
        qv[u] = qtab[kk[u]] if kk[u] >= 0 else np.nan
    bx = 0
    while bx < block_flow.shape[1]:
        bx2, fu, fv, u0, u1, a, b = _flow_run(block_flow, by, bx, block, w)
        sv = min(max(v - fv, 0), h - 1)
        base_row, fringe_row = base[sv], fringe[sv]
        for u in range(u0, a):
            row[u] = _shade(qv[u], base_row[0], fringe_row[0], qbar, scale, amb)
        _shade_run(row, qv, a, b, a - fu, base_row, fringe_row, qbar, scale, amb)
        for u in range(b, u1):
            row[u] = _shade(qv[u], base_row[w - 1], fringe_row[w - 1], qbar, scale, amb)
        bx = bx2


@nb.njit(cache=True, fastmath=FAST, inline="always")
def _deviates(z: F32, u0: int, u1: int, table: F32, state: U64, r: np.uint64, j: int
              ) -> tuple[np.uint64, int]:
    """z[u0 .. u1 − 1] = the next normal deviates, four per generator step; (r, j) carries the
    current step's bits and how many of its four are used. Returns the new (r, j)."""
    for u in range(u0, u1):
        if j == 4:
            r = _next(state)
            j = 0
        z[u] = table[(r >> np.uint64(16 * j)) & np.uint64(0xFFFF)]
        j += 1
    return r, j


@nb.njit(cache=True, fastmath=FAST, error_model="numpy")
def _adc_run(out_row: DN, row: F32, z: F32, u0: int, u1: int, g: float, read2: float,
             maxv: int) -> None:
    """out_row[u] = ADC(row[u], z[u]) for u0 ≤ u < u1 (vectorised)."""
    for u in range(u0, u1):
        out_row[u] = _adc(row[u], g, read2, maxv, z[u])


@nb.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def moving_frame(out: F32 | DN, noisy: bool, band: F32, zbuf: F32, kk: I32, qv: F32, nd: F32,
                 base: F32, fringe: F32, block_flow: I64, block: int, n_add: float, d_add: float,
                 k_over_w: float, shift_frac: float, width_p: float, qtab: F32, qbar: float,
                 scale: float, amb: float, g: float, read2: float, maxv: int, table: F32,
                 state: U64) -> None:
    """A frame of a rigidly translated scene: the noise-free mean (``noisy`` False, ``out``
    float32) or the noisy, quantised frame (``noisy`` True, ``out`` uint8/uint16), in one pass.

    Each ``block``×``block`` tile takes the rest-pose samples it now sees through one backward
    step of its (integer, per-tile) image flow ``block_flow`` (tiles_y, tiles_x, 2); the
    projector column of each sample moved by δ is exact: x_p = (N0 + α·δ)/(D0 + γ·δ) with
    nd = (N0, D0) per pixel ((2, H, W) float32) and n_add = α·δ, d_add = γ·δ.
    base, fringe: (H, W) float32 (0 where unlit); qtab: projector output over one period.
    band: (block, W) float32 scratch (one row of tiles); zbuf, qv: (W,) float32 and kk: (W,) int32
    scratch. The noise is drawn tile by tile (row-major within a tile, tiles row-major).
    """
    h, w = base.shape
    r = np.uint64(0)
    j = 4
    for by in range(block_flow.shape[0]):
        rows = min(block, h - by * block)
        for i in range(rows):
            _scene_row(band[i], kk, qv, by * block + i, nd, base, fringe, block_flow, block, n_add,
                       d_add, k_over_w, shift_frac, width_p, qtab, qbar, scale, amb)
        if not noisy:
            for i in range(rows):
                out[by * block + i, :] = band[i]
            continue
        for bx in range(block_flow.shape[1]):
            u0, u1 = bx * block, min((bx + 1) * block, w)
            for i in range(rows):
                r, j = _deviates(zbuf, u0, u1, table, state, r, j)
                _adc_run(out[by * block + i], band[i], zbuf, u0, u1, g, read2, maxv)
