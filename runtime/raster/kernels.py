"""Numba tile rasterizer, forward and backward (docs/design.md section 6): the one implementation shared by
training (through `nehad.splat.rasterize`) and the torch-free runtime.

Each tile (16x16 pixels) is one iteration of the parallel loop; numba gives each thread one
contiguous block of the loop, so the tiles come in the order of `interleaved_tiles` (every
thread gets every T-th row of tiles). Inside a tile the loop runs over the tile's Gaussians
front to back; for each, over the tile rows that the bounding box of its alpha >= 1/255 ellipse
covers, and in each row over all 16 pixels at once: a fixed 16-lane loop that LLVM turns into
one 512-bit SIMD loop on this machine (docs/performance.md: with 16-lane rows the kernel drew
the 100k/800x800 frame in 24 ms where 8-lane half rows, skipped by the ellipse's columns, took
37 ms).
Pixels outside the ellipse have alpha < 1/255 and are skipped by the alpha test. Per pixel:

    alpha = min(0.99, opacity * exp(-d^T conic d / 2)); skipped when alpha < 1/255;
    the pixel stops before the Gaussian that would bring T below 1e-4;
    rgb = sum c alpha T + T_final * background; alpha_out = 1 - T_final;
    depth = sum z alpha T / max(alpha_out, eps).

The backward pass walks the same order front to back. With P_i the colour accumulated up to and
including Gaussian i and C the total (background excluded),

    dL/dalpha_i = sum_ch g_ch (c_i,ch T_i - (C_ch - P_i,ch + T_final bg_ch) / (1 - alpha_i))
                  + g_alpha T_final / (1 - alpha_i),

which needs no division of T by (1 - alpha) and replays the forward's stopping index exactly.
Gradients are written per (tile, Gaussian) entry and summed per Gaussian afterwards, so no two
threads write the same memory.

A tile's per-pixel state lives in ONE array, state[row, field, lane]: with a separate array
per field LLVM needs run-time alias checks between all of them and gives up vectorising.
"""

from __future__ import annotations

import numba
import numpy as np

from .fastexp import fast_exp
from .intrinsics import EXACT_FASTMATH, fma32, prefetch_row
from .binning import P_B, P_CA, P_CB, P_CC, P_G, P_MX, P_MY, P_OP, P_R, P_ROW0, P_ROW1, P_Z
from .projection import TILE

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_HALF = np.float32(0.5)
_ALPHA_MAX = np.float32(0.99)
_ALPHA_MIN = np.float32(1.0 / 255.0)
_T_MIN = np.float32(1e-4)
_DEPTH_EPS = np.float32(1e-8)
_NEVER = np.float32(2 ** 30)  # 'never stopped'; stop indices are kept as float32 (exact below 2^24)
# per-entry gradient columns
N_GRAD = 9  # d mean2d (2), d conic (3), d colour (3), d opacity (1)
_D_MX, _D_MY, _D_CA, _D_CB, _D_CC, _D_R, _D_G, _D_B, _D_OP = range(N_GRAD)

_SATURATION_CHECK = 16  # entries between checks for fully stopped rows
#: Tile entries ahead whose Gaussian record is prefetched (records are read in depth order,
#: scattered over the packed array; 2 ahead took 24.7 -> 23.8 ms at 100k/800x800).
_PREFETCH_AHEAD = 2

#: Fast-math flags of the forward kernel: all of LLVM's but 'contract'. With contraction allowed,
#: the kernel JIT-compiled in one process and the same kernel loaded from numba's cache in
#: another fused different multiply-adds (up to 4e-7 apart, enough to flip one 8-bit pixel of a
#: 24-frame video between a single-process render and a render by worker processes). Without
#: it, every process computes bit-identical frames.
_FORWARD_FASTMATH = {"nnan", "ninf", "nsz", "arcp", "afn", "reassoc"}


def interleaved_tiles(tiles_x: int, tiles_y: int, threads: int) -> np.ndarray:
    """The order the kernels visit tiles in: numba hands each of the `threads` threads one
    contiguous block of the loop (static scheduling), so the tiles are listed by tile row modulo
    `threads` first: each thread then draws every threads-th row of the whole image instead of
    one band of it, and an object in the lower half of the picture is shared between them
    (a 15k-Gaussian MuJoCo model at 800x800: 2 threads drew 1.45x faster than one in bands)."""
    rows = np.arange(tiles_y)
    rows = np.concatenate([rows[rows % threads == k] for k in range(max(1, threads))])
    return (rows[:, None] * tiles_x + np.arange(tiles_x)[None, :]).reshape(-1).astype(np.int64)


# fields of the forward state
_T, _R, _G, _B, _D, _STOP = 0, 1, 2, 3, 4, 5
# fields of the backward state: running T and colour still to come, then per-pixel constants
_BT, _REST_R, _REST_G, _REST_B, _GR, _GG, _GB, _GA, _TFIN, _BSTOP = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9


@numba.njit(inline="always")
def _unpack(rec):
    """mean2d, conic, opacity and colour of a packed record (see `binning.PACKED_WIDTH`)."""
    return (rec[P_MX], rec[P_MY], rec[P_CA], rec[P_CB], rec[P_CC], rec[P_OP], rec[P_R], rec[P_G],
            rec[P_B])


@numba.njit(inline="always")
def _rows_in_tile(rec, y0):
    """Tile-local rows [r0, r1] of the Gaussian's ellipse box."""
    r0 = max(np.int32(rec[P_ROW0]) - y0, 0)
    r1 = min(np.int32(rec[P_ROW1]) - y0, TILE - 1)
    return r0, r1


@numba.njit(inline="always")
def _lane_offsets():
    """0, 1, ..., TILE-1 as float32: a pixel's column offset inside its tile row."""
    return np.arange(TILE).astype(np.float32)


@numba.njit(parallel=True, fastmath=_FORWARD_FASTMATH, cache=True)
def forward_kernel(tile_order, tile_offsets, gauss_ids, packed, width, height, background,
                   out_rgb, out_final_t, out_depth, out_stop):
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    bg0, bg1, bg2 = np.float32(background[0]), np.float32(background[1]), np.float32(background[2])
    for task in numba.prange(ntx * nty):
        tile = tile_order[task]
        x0 = (tile % ntx) * TILE
        y0 = (tile // ntx) * TILE
        st = np.zeros((TILE, 6, TILE), np.float32)
        lanes = _lane_offsets()
        for r in range(TILE):
            for jj in range(TILE):
                st[r, _T, jj] = _F1
                if x0 + jj < width and y0 + r < height:
                    st[r, _STOP, jj] = _NEVER
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        row_lo = 0
        row_hi = TILE - 1
        for k in range(start, end):
            local = np.float32(k - start)
            # the tile is done once all its pixels have stopped (pixels outside the image stop at
            # once), and only rows row_lo..row_hi still have running pixels; both are checked
            # every _SATURATION_CHECK entries rather than inside the SIMD loop. Done rows
            # between them are still drawn (masked by their stop index): a per-row skip cost
            # more in branches than it saved (19.6 vs 20.9 ms at 100k/800x800), the range
            # bound costs nothing (19.2 -> 18.0 ms)
            if (k - start) % _SATURATION_CHECK == 0:
                row_lo = TILE
                row_hi = -1
                for r in range(TILE):
                    latest = _F0  # a pixel still running has stop == _NEVER, the maximum
                    for jj in range(TILE):
                        latest = max(latest, st[r, _STOP, jj])
                    if latest == _NEVER:
                        row_lo = min(row_lo, r)
                        row_hi = max(row_hi, r)
                if row_hi < 0:
                    break
            if k + _PREFETCH_AHEAD < end:
                prefetch_row(packed, gauss_ids[k + _PREFETCH_AHEAD])
            rec = packed[gauss_ids[k]]
            mx, my, ca, cb, cc, op, cr, cg, cbl = _unpack(rec)
            z = rec[P_Z]
            r0, r1 = _rows_in_tile(rec, y0)
            dx0 = np.float32(x0) + _HALF - mx
            half_ca = _HALF * ca
            for r in range(max(r0, row_lo), min(r1, row_hi) + 1):
                dy = np.float32(y0 + r) + _HALF - my
                minus_qyy = -(_HALF * cc * dy * dy)
                cbdy = cb * dy
                for jj in range(TILE):
                    dx = dx0 + lanes[jj]
                    # -(ca dx^2 / 2 + cb dx dy + cc dy^2 / 2)
                    power = fma32(fma32(half_ca, dx, cbdy), -dx, minus_qyy)
                    alpha = min(_ALPHA_MAX, op * fast_exp(power))
                    t = st[r, _T, jj]
                    t_next = t * (_F1 - alpha)
                    live = (alpha >= _ALPHA_MIN) and (local < st[r, _STOP, jj])
                    halt = live and (t_next < _T_MIN)
                    go = live and not halt
                    w = alpha * t if go else _F0
                    st[r, _R, jj] = fma32(w, cr, st[r, _R, jj])
                    st[r, _G, jj] = fma32(w, cg, st[r, _G, jj])
                    st[r, _B, jj] = fma32(w, cbl, st[r, _B, jj])
                    st[r, _D, jj] = fma32(w, z, st[r, _D, jj])
                    st[r, _T, jj] = t_next if go else t
                    st[r, _STOP, jj] = local if halt else st[r, _STOP, jj]
        for r in range(min(TILE, height - y0)):
            for j in range(min(TILE, width - x0)):
                y, x = y0 + r, x0 + j
                t = st[r, _T, j]
                out_rgb[y, x, 0] = st[r, _R, j] + t * bg0
                out_rgb[y, x, 1] = st[r, _G, j] + t * bg1
                out_rgb[y, x, 2] = st[r, _B, j] + t * bg2
                out_final_t[y, x] = t
                out_depth[y, x] = st[r, _D, j] / max(_F1 - t, _DEPTH_EPS)
                out_stop[y, x] = np.int32(st[r, _STOP, j])


@numba.njit(parallel=True, fastmath=EXACT_FASTMATH, cache=True)
def backward_kernel(tile_order, tile_offsets, gauss_ids, packed, width, height, out_rgb,
                    out_final_t, out_stop, grad_rgb, grad_alpha, entry_grads):
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    for task in numba.prange(ntx * nty):
        tile = tile_order[task]
        x0 = (tile % ntx) * TILE
        y0 = (tile // ntx) * TILE
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        if end == start:
            continue
        # pixels outside the image keep zero gradients and stop = 0: they contribute nothing
        st = np.zeros((TILE, 10, TILE), np.float32)
        lanes = _lane_offsets()
        # the largest stopping index of each row: entries at or past it touch none of its pixels
        row_last = np.zeros(TILE, np.float32)
        for r in range(TILE):
            for j in range(TILE):
                st[r, _BT, j] = _F1
                y, x = y0 + r, x0 + j
                if x < width and y < height:
                    # colour still to come behind Gaussian i: C - P_i + T_final bg, P_0 = 0
                    st[r, _REST_R, j] = out_rgb[y, x, 0]
                    st[r, _REST_G, j] = out_rgb[y, x, 1]
                    st[r, _REST_B, j] = out_rgb[y, x, 2]
                    st[r, _GR, j] = grad_rgb[y, x, 0]
                    st[r, _GG, j] = grad_rgb[y, x, 1]
                    st[r, _GB, j] = grad_rgb[y, x, 2]
                    st[r, _GA, j] = grad_alpha[y, x]
                    st[r, _TFIN, j] = out_final_t[y, x]
                    s = np.float32(min(out_stop[y, x], end - start))
                    st[r, _BSTOP, j] = s
                    row_last[r] = max(row_last[r], s)
        last = np.int64(row_last.max())
        # per-lane gradient sums of the current entry, summed over lanes once per entry: with
        # scalar sums LLVM reduced the 16 lanes after every row (9 horizontal reductions per
        # row; 13.0 -> 8.3 ms at 20k/400x400 without them)
        acc = np.zeros((N_GRAD, TILE), np.float32)
        for k in range(start, start + last):
            local = np.float32(k - start)
            if k + _PREFETCH_AHEAD < end:
                prefetch_row(packed, gauss_ids[k + _PREFETCH_AHEAD])
            rec = packed[gauss_ids[k]]
            mx, my, ca, cb, cc, op, cr, cg, cbl = _unpack(rec)
            acc[:, :] = _F0
            r0, r1 = _rows_in_tile(rec, y0)
            dx0 = np.float32(x0) + _HALF - mx
            half_ca = _HALF * ca
            for r in range(r0, r1 + 1):
                if local >= row_last[r]:
                    continue
                dy = np.float32(y0 + r) + _HALF - my
                minus_qyy = -(_HALF * cc * dy * dy)
                half_dy2 = _HALF * dy * dy
                cbdy = cb * dy
                ccdy = cc * dy
                for jj in range(TILE):
                    dx = dx0 + lanes[jj]
                    # the forward kernel's exponent, rounded the same way
                    power = fma32(fma32(half_ca, dx, cbdy), -dx, minus_qyy)
                    gauss = fast_exp(power)
                    raw = op * gauss
                    alpha = min(_ALPHA_MAX, raw)
                    t = st[r, _BT, jj]
                    live = (alpha >= _ALPHA_MIN) and (local < st[r, _BSTOP, jj])
                    w = alpha * t if live else _F0
                    one_minus = _F1 - alpha
                    inv = _F1 / one_minus
                    gr = st[r, _GR, jj]
                    gg = st[r, _GG, jj]
                    gb = st[r, _GB, jj]
                    rr = fma32(-w, cr, st[r, _REST_R, jj])
                    rg = fma32(-w, cg, st[r, _REST_G, jj])
                    rb = fma32(-w, cbl, st[r, _REST_B, jj])
                    # sum_c g_c (c t - rest_c / (1 - alpha)) + g_alpha T_final / (1 - alpha)
                    d_alpha = fma32(gr, fma32(cr, t, -(rr * inv)),
                                    fma32(gg, fma32(cg, t, -(rg * inv)),
                                          fma32(gb, fma32(cbl, t, -(rb * inv)),
                                                st[r, _GA, jj] * st[r, _TFIN, jj] * inv)))
                    acc[_D_R, jj] = fma32(gr, w, acc[_D_R, jj])
                    acc[_D_G, jj] = fma32(gg, w, acc[_D_G, jj])
                    acc[_D_B, jj] = fma32(gb, w, acc[_D_B, jj])
                    d_raw = d_alpha if (live and raw < _ALPHA_MAX) else _F0
                    acc[_D_OP, jj] = fma32(d_raw, gauss, acc[_D_OP, jj])
                    d_pow = d_raw * raw
                    acc[_D_CA, jj] = fma32(-(_HALF * d_pow * dx), dx, acc[_D_CA, jj])
                    acc[_D_CB, jj] = fma32(-(d_pow * dx), dy, acc[_D_CB, jj])
                    acc[_D_CC, jj] = fma32(-d_pow, half_dy2, acc[_D_CC, jj])
                    acc[_D_MX, jj] = fma32(d_pow, fma32(ca, dx, cbdy), acc[_D_MX, jj])
                    acc[_D_MY, jj] = fma32(d_pow, fma32(cb, dx, ccdy), acc[_D_MY, jj])
                    st[r, _REST_R, jj] = rr
                    st[r, _REST_G, jj] = rg
                    st[r, _REST_B, jj] = rb
                    st[r, _BT, jj] = t * one_minus if live else t
            for c in range(N_GRAD):
                total = _F0
                for jj in range(TILE):
                    total += acc[c, jj]
                entry_grads[k, c] = total


@numba.njit(cache=True)
def sum_entry_grads(gauss_ids, entry_grads, n_gaussians):
    """Sum per-(tile, Gaussian) gradients into per-Gaussian rows."""
    out = np.zeros((n_gaussians, N_GRAD), np.float32)
    for k in range(gauss_ids.shape[0]):
        g = gauss_ids[k]
        for c in range(N_GRAD):
            out[g, c] += entry_grads[k, c]
    return out
