"""Numba tile rasterizer, forward and backward (docs/design.md section 6): the one implementation shared by
training (through `nehad.splat.rasterize`) and the torch-free runtime.

Each tile (16x16 pixels) is one parallel task (handed out a few tiles at a time, so that the
threads share the heavy tiles). Inside a tile the loop runs over the tile's Gaussians front to
back; for each, over the rows and the 8-pixel half rows that the bounding box of its
alpha >= 1/255 ellipse covers (fixed per Gaussian, so the loop counts are predictable: an exact
span per row cost more in branches and square roots than the lanes it saved). The inner loop is a
fixed 8-lane loop that LLVM turns into SIMD (the layout measured in ../shared/notes/cpu-raster.md);
pixels outside the ellipse have alpha < 1/255 and are skipped by the alpha test. Per pixel:

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

A tile's per-pixel state lives in ONE array, state[row, run, field, lane]: with a separate array
per field LLVM needs run-time alias checks between all of them and gives up vectorising.
"""

from __future__ import annotations

import numba
import numpy as np

from .fastexp import fast_exp
from .binning import (P_B, P_CA, P_CB, P_CC, P_COL0, P_COL1, P_G, P_MX, P_MY, P_OP, P_R, P_ROW0,
                      P_ROW1, P_Z)
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

_LANES = 8  # pixels per SIMD run; a tile row is two runs
_RUNS = TILE // _LANES
_SATURATION_CHECK = 16  # entries between checks for fully stopped runs
#: Tiles per parallel task (numba.parallel_chunksize): threads take tasks as they finish, so a
#: thread that drew the busy centre of the image does not leave the other idle (an even static
#: split took 14.4 ms where 4 tiles per task took 9.8 ms, 20k Gaussians at 400x400, 2 threads).
TILES_PER_TASK = 4

#: Fast-math flags of the forward kernel: all of LLVM's but 'contract'. With contraction allowed,
#: the kernel JIT-compiled in one process and the same kernel loaded from numba's cache in
#: another fused different multiply-adds (up to 4e-7 apart, enough to flip one 8-bit pixel of a
#: 24-frame video between a single-process render and a render by worker processes). Without
#: it, every process computes bit-identical frames.
_FORWARD_FASTMATH = {"nnan", "ninf", "nsz", "arcp", "afn", "reassoc"}

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
def _box_in_tile(rec, x0, y0):
    """Tile-local rows [r0, r1] and half rows [h0, h1] of the Gaussian's ellipse box."""
    r0 = max(np.int32(rec[P_ROW0]) - y0, 0)
    r1 = min(np.int32(rec[P_ROW1]) - y0, TILE - 1)
    h0 = max(np.int32(rec[P_COL0]) - x0, 0) // _LANES
    h1 = min(np.int32(rec[P_COL1]) - x0, TILE - 1) // _LANES
    return r0, r1, h0, h1


@numba.njit(parallel=True, fastmath=_FORWARD_FASTMATH, cache=True)
def forward_kernel(tile_offsets, gauss_ids, packed, width, height, background,
                   out_rgb, out_final_t, out_depth, out_stop):
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    bg0, bg1, bg2 = np.float32(background[0]), np.float32(background[1]), np.float32(background[2])
    for tile in numba.prange(ntx * nty):
        x0 = (tile % ntx) * TILE
        y0 = (tile // ntx) * TILE
        st = np.zeros((TILE, _RUNS, 6, _LANES), np.float32)
        # runs whose pixels have all stopped (pixels outside the image stop at once); refreshed
        # every _SATURATION_CHECK entries rather than counted inside the SIMD loop
        run_open = np.ones((TILE, _RUNS), np.bool_)
        for r in range(TILE):
            for h in range(_RUNS):
                for jj in range(_LANES):
                    st[r, h, _T, jj] = _F1
                    if x0 + h * _LANES + jj < width and y0 + r < height:
                        st[r, h, _STOP, jj] = _NEVER
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        for k in range(start, end):
            local = np.float32(k - start)
            if (k - start) % _SATURATION_CHECK == 0:
                n_open = 0
                for r in range(TILE):
                    for h in range(_RUNS):
                        latest = _F0  # a pixel still running has stop == _NEVER, the maximum
                        for jj in range(_LANES):
                            latest = max(latest, st[r, h, _STOP, jj])
                        still = latest == _NEVER
                        run_open[r, h] = still
                        n_open += still
                if n_open == 0:
                    break
            rec = packed[gauss_ids[k]]
            mx, my, ca, cb, cc, op, cr, cg, cbl = _unpack(rec)
            z = rec[P_Z]
            r0, r1, h0, h1 = _box_in_tile(rec, x0, y0)
            for r in range(r0, r1 + 1):
                dy = np.float32(y0 + r) + _HALF - my
                qyy = _HALF * cc * dy * dy
                cbdy = cb * dy
                for h in range(h0, h1 + 1):
                    if not run_open[r, h]:
                        continue
                    dx0 = np.float32(x0 + h * _LANES) + _HALF - mx
                    for jj in range(_LANES):
                        dx = dx0 + np.float32(jj)
                        power = -(_HALF * ca * dx * dx + qyy) - cbdy * dx
                        alpha = min(_ALPHA_MAX, op * fast_exp(power))
                        t = st[r, h, _T, jj]
                        t_next = t * (_F1 - alpha)
                        live = (alpha >= _ALPHA_MIN) and (local < st[r, h, _STOP, jj])
                        halt = live and (t_next < _T_MIN)
                        go = live and not halt
                        w = alpha * t if go else _F0
                        st[r, h, _R, jj] += w * cr
                        st[r, h, _G, jj] += w * cg
                        st[r, h, _B, jj] += w * cbl
                        st[r, h, _D, jj] += w * z
                        st[r, h, _T, jj] = t_next if go else t
                        st[r, h, _STOP, jj] = local if halt else st[r, h, _STOP, jj]
        for r in range(min(TILE, height - y0)):
            for j in range(min(TILE, width - x0)):
                h, jj = j // _LANES, j % _LANES
                y, x = y0 + r, x0 + j
                t = st[r, h, _T, jj]
                out_rgb[y, x, 0] = st[r, h, _R, jj] + t * bg0
                out_rgb[y, x, 1] = st[r, h, _G, jj] + t * bg1
                out_rgb[y, x, 2] = st[r, h, _B, jj] + t * bg2
                out_final_t[y, x] = t
                out_depth[y, x] = st[r, h, _D, jj] / max(_F1 - t, _DEPTH_EPS)
                out_stop[y, x] = np.int32(st[r, h, _STOP, jj])


@numba.njit(parallel=True, fastmath=True, cache=True)
def backward_kernel(tile_offsets, gauss_ids, packed, width, height, out_rgb, out_final_t,
                    out_stop, grad_rgb, grad_alpha, entry_grads):
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    for tile in numba.prange(ntx * nty):
        x0 = (tile % ntx) * TILE
        y0 = (tile // ntx) * TILE
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        if end == start:
            continue
        # pixels outside the image keep zero gradients and stop = 0: they contribute nothing
        st = np.zeros((TILE, _RUNS, 10, _LANES), np.float32)
        # the largest stopping index of each run: entries at or past it touch none of its pixels
        run_last = np.zeros((TILE, _RUNS), np.float32)
        for r in range(TILE):
            for j in range(TILE):
                h, jj = j // _LANES, j % _LANES
                st[r, h, _BT, jj] = _F1
                y, x = y0 + r, x0 + j
                if x < width and y < height:
                    # colour still to come behind Gaussian i: C - P_i + T_final bg, P_0 = 0
                    st[r, h, _REST_R, jj] = out_rgb[y, x, 0]
                    st[r, h, _REST_G, jj] = out_rgb[y, x, 1]
                    st[r, h, _REST_B, jj] = out_rgb[y, x, 2]
                    st[r, h, _GR, jj] = grad_rgb[y, x, 0]
                    st[r, h, _GG, jj] = grad_rgb[y, x, 1]
                    st[r, h, _GB, jj] = grad_rgb[y, x, 2]
                    st[r, h, _GA, jj] = grad_alpha[y, x]
                    st[r, h, _TFIN, jj] = out_final_t[y, x]
                    s = np.float32(min(out_stop[y, x], end - start))
                    st[r, h, _BSTOP, jj] = s
                    run_last[r, h] = max(run_last[r, h], s)
        last = np.int64(run_last.max())
        for k in range(start, start + last):
            local = np.float32(k - start)
            rec = packed[gauss_ids[k]]
            mx, my, ca, cb, cc, op, cr, cg, cbl = _unpack(rec)
            d_mx = _F0
            d_my = _F0
            d_ca = _F0
            d_cb = _F0
            d_cc = _F0
            d_r = _F0
            d_g = _F0
            d_b = _F0
            d_op = _F0
            r0, r1, h0, h1 = _box_in_tile(rec, x0, y0)
            for r in range(r0, r1 + 1):
                dy = np.float32(y0 + r) + _HALF - my
                qyy = _HALF * cc * dy * dy
                cbdy = cb * dy
                for h in range(h0, h1 + 1):
                    if local >= run_last[r, h]:
                        continue
                    dx0 = np.float32(x0 + h * _LANES) + _HALF - mx
                    for jj in range(_LANES):
                        dx = dx0 + np.float32(jj)
                        power = -(_HALF * ca * dx * dx + qyy) - cbdy * dx
                        gauss = fast_exp(power)
                        raw = op * gauss
                        alpha = min(_ALPHA_MAX, raw)
                        t = st[r, h, _BT, jj]
                        live = (alpha >= _ALPHA_MIN) and (local < st[r, h, _BSTOP, jj])
                        w = alpha * t if live else _F0
                        one_minus = _F1 - alpha
                        inv = _F1 / one_minus
                        gr = st[r, h, _GR, jj]
                        gg = st[r, h, _GG, jj]
                        gb = st[r, h, _GB, jj]
                        rr = st[r, h, _REST_R, jj] - w * cr
                        rg = st[r, h, _REST_G, jj] - w * cg
                        rb = st[r, h, _REST_B, jj] - w * cbl
                        d_alpha = (gr * (cr * t - rr * inv) + gg * (cg * t - rg * inv)
                                   + gb * (cbl * t - rb * inv)
                                   + st[r, h, _GA, jj] * st[r, h, _TFIN, jj] * inv)
                        d_r += gr * w
                        d_g += gg * w
                        d_b += gb * w
                        d_raw = d_alpha if (live and raw < _ALPHA_MAX) else _F0
                        d_op += d_raw * gauss
                        d_pow = d_raw * raw
                        d_ca -= _HALF * d_pow * dx * dx
                        d_cb -= d_pow * dx * dy
                        d_cc -= _HALF * d_pow * dy * dy
                        d_mx += d_pow * (ca * dx + cb * dy)
                        d_my += d_pow * (cc * dy + cb * dx)
                        st[r, h, _REST_R, jj] = rr
                        st[r, h, _REST_G, jj] = rg
                        st[r, h, _REST_B, jj] = rb
                        st[r, h, _BT, jj] = t * one_minus if live else t
            entry_grads[k, 0] = d_mx
            entry_grads[k, 1] = d_my
            entry_grads[k, 2] = d_ca
            entry_grads[k, 3] = d_cb
            entry_grads[k, 4] = d_cc
            entry_grads[k, 5] = d_r
            entry_grads[k, 6] = d_g
            entry_grads[k, 7] = d_b
            entry_grads[k, 8] = d_op


@numba.njit(cache=True)
def sum_entry_grads(gauss_ids, entry_grads, n_gaussians):
    """Sum per-(tile, Gaussian) gradients into per-Gaussian rows."""
    out = np.zeros((n_gaussians, N_GRAD), np.float32)
    for k in range(gauss_ids.shape[0]):
        g = gauss_ids[k]
        for c in range(N_GRAD):
            out[g, c] += entry_grads[k, c]
    return out
