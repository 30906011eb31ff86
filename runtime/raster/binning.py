"""Tile binning: which Gaussians touch which 16x16 tile, front to back (docs/design.md section 6).

A Gaussian belongs to every tile its 3-sigma box overlaps (the 3DGS rule), intersected with the
tiles where its alpha can reach 1/255 at all: the ellipse d^T conic d <= 2 ln(255 opacity). The
intersection changes no pixel: outside that ellipse alpha < 1/255 and is skipped anyway.
The same ellipse's bounding box gives each Gaussian the pixel rows it can touch, which the
kernels use to skip tile rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ..memory import check_tile_lists
from .projection import TILE

ALPHA_MIN = 1.0 / 255.0
# Slack on the opacity-aware ellipse so that float32 rounding in the kernels never reaches past it.
_EXTENT_SLACK_REL = 1e-3
_EXTENT_SLACK_PX = 0.05


# Columns of the packed per-Gaussian record: everything the kernels read about one Gaussian sits
# in one 64-byte cache line (with seven separate arrays, cache misses dominated the frame time).
# ROW0..ROW1 are the image rows whose pixel centres lie in the bounding box of the ellipse
# d^T conic d <= 2 ln(255 opacity) (with slack), outside which alpha < 1/255.
P_MX, P_MY, P_CA, P_CB, P_CC, P_OP, P_R, P_G, P_B, P_Z, P_ROW0, P_ROW1 = range(12)
PACKED_WIDTH = 16


@dataclass
class TileBins:
    """tile_offsets (n_tiles + 1,) int64; gauss_ids (M,) int32, each tile's run sorted by depth;
    packed (N, 16) float32 records: mean2d, conic, opacity, colour, depth, and the first and
    last pixel row the Gaussian can touch: the bounding box of the ellipse
    d^T conic d <= 2 ln(255 opacity) (with slack), outside which alpha < 1/255."""

    tile_offsets: np.ndarray
    gauss_ids: np.ndarray
    packed: np.ndarray
    width: int
    height: int

    @property
    def tiles_x(self) -> int:
        return (self.width + TILE - 1) // TILE

    @property
    def tiles_y(self) -> int:
        return (self.height + TILE - 1) // TILE


@numba.njit(parallel=True, cache=True)
def _tile_rects(means2d, conics, colors, opacities, depths, radii, width, height, rects, packed):
    n = means2d.shape[0]
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    for i in numba.prange(n):
        rects[i, 0] = 0
        rects[i, 1] = 0
        rects[i, 2] = 0
        rects[i, 3] = 0
        r = radii[i]
        op = np.float64(opacities[i])
        if r <= 0 or not (op * 255.0 > 1.0):
            continue
        mx, my = np.float64(means2d[i, 0]), np.float64(means2d[i, 1])
        a, b, c = np.float64(conics[i, 0]), np.float64(conics[i, 1]), np.float64(conics[i, 2])
        det = a * c - b * b
        # non-finite inputs are invisible (float -> int conversions below would be undefined)
        z = np.float64(depths[i])
        if not (det > 0.0 and a > 0.0 and abs(mx) < 1e9 and abs(my) < 1e9 and det < 1e30
                and op <= 1.0 and r < 1e8 and 0.0 < z < 1e30):
            continue
        two_tau = 2.0 * math.log(255.0 * op)
        ex = math.sqrt(two_tau * c / det) * (1.0 + _EXTENT_SLACK_REL) + _EXTENT_SLACK_PX
        ey = math.sqrt(two_tau * a / det) * (1.0 + _EXTENT_SLACK_REL) + _EXTENT_SLACK_PX
        # 3DGS rect of the 3-sigma box
        tx0 = min(ntx, max(0, int(math.floor((mx - 0.5 - r) / TILE))))
        tx1 = min(ntx, max(0, int(math.floor((mx - 0.5 + r + TILE - 1) / TILE))))
        ty0 = min(nty, max(0, int(math.floor((my - 0.5 - r) / TILE))))
        ty1 = min(nty, max(0, int(math.floor((my - 0.5 + r + TILE - 1) / TILE))))
        # pixels whose centre lies inside the opacity-aware ellipse's box
        i0 = max(0, int(math.ceil(mx - ex - 0.5)))
        i1 = min(width - 1, int(math.floor(mx + ex - 0.5)))
        j0 = max(0, int(math.ceil(my - ey - 0.5)))
        j1 = min(height - 1, int(math.floor(my + ey - 0.5)))
        if i1 < i0 or j1 < j0:
            continue
        tx0 = max(tx0, i0 // TILE)
        tx1 = min(tx1, i1 // TILE + 1)
        ty0 = max(ty0, j0 // TILE)
        ty1 = min(ty1, j1 // TILE + 1)
        if tx1 <= tx0 or ty1 <= ty0:
            continue
        rects[i, 0] = tx0
        rects[i, 1] = tx1
        rects[i, 2] = ty0
        rects[i, 3] = ty1
        rec = packed[i]
        rec[P_MX] = means2d[i, 0]
        rec[P_MY] = means2d[i, 1]
        rec[P_CA] = conics[i, 0]
        rec[P_CB] = conics[i, 1]
        rec[P_CC] = conics[i, 2]
        rec[P_OP] = opacities[i]
        rec[P_R] = colors[i, 0]
        rec[P_G] = colors[i, 1]
        rec[P_B] = colors[i, 2]
        rec[P_Z] = depths[i]
        rec[P_ROW0] = j0
        rec[P_ROW1] = j1


@numba.njit(cache=True)
def _count_pairs(rects):
    """Number of (Gaussian, tile) entries of the tile lists (invisible Gaussians have empty
    rectangles)."""
    total = 0
    for i in range(rects.shape[0]):
        total += np.int64(rects[i, 1] - rects[i, 0]) * np.int64(rects[i, 3] - rects[i, 2])
    return total


@numba.njit(parallel=True, cache=True)
def _fill_bins(order, rects, ntx, n_tiles, n_chunks):
    """Scatter depth-ordered Gaussians into per-tile runs; chunk c of `order` is handled by one
    thread, and chunk c's entries go after chunk c-1's in every tile, so runs stay depth-sorted."""
    n = order.shape[0]
    per = (n + n_chunks - 1) // n_chunks
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in numba.prange(n_chunks):
        for o in range(c * per, min(n, (c + 1) * per)):
            g = order[o]
            for ty in range(rects[g, 2], rects[g, 3]):
                for tx in range(rects[g, 0], rects[g, 1]):
                    counts[c, ty * ntx + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    cursor = np.zeros((n_chunks, n_tiles), np.int64)
    total = 0
    for t in range(n_tiles):
        offsets[t] = total
        for c in range(n_chunks):
            cursor[c, t] = total
            total += counts[c, t]
    offsets[n_tiles] = total
    ids = np.empty(total, np.int32)
    for c in numba.prange(n_chunks):
        for o in range(c * per, min(n, (c + 1) * per)):
            g = order[o]
            for ty in range(rects[g, 2], rects[g, 3]):
                for tx in range(rects[g, 0], rects[g, 1]):
                    t = ty * ntx + tx
                    ids[cursor[c, t]] = g
                    cursor[c, t] += 1
    return offsets, ids


@numba.njit(cache=True)
def _radix_argsort_depth(ids, depths):
    """`ids` ordered by depths[ids] (all > 0), stable: two LSD passes over the 16-bit halves of
    the float32 bit patterns, which order like the floats for positive values."""
    n = ids.shape[0]
    keys = depths.view(np.uint32)
    src = ids.copy()
    dst = np.empty_like(ids)
    for shift in (0, 16):
        counts = np.zeros(65537, np.int64)
        for i in range(n):
            counts[((keys[src[i]] >> shift) & 0xFFFF) + 1] += 1
        for b in range(65536):
            counts[b + 1] += counts[b]
        for i in range(n):
            d = (keys[src[i]] >> shift) & 0xFFFF
            dst[counts[d]] = src[i]
            counts[d] += 1
        src, dst = dst, src
    return src


def bin_gaussians(means2d, conics, colors, opacities, depths, radii, width, height) -> TileBins:
    """Bin projected Gaussians into 16x16 tiles, each tile's list sorted front to back.

    Inputs are float32 arrays (radii int32) as `Projected` holds them."""
    n = means2d.shape[0]
    rects = np.empty((n, 4), np.int32)
    packed = np.empty((n, PACKED_WIDTH), np.float32)
    _tile_rects(means2d, conics, colors, opacities, depths, radii, int(width), int(height),
                rects, packed)
    visible = np.flatnonzero((rects[:, 1] > rects[:, 0]) & (rects[:, 3] > rects[:, 2]))
    order = _radix_argsort_depth(visible.astype(np.int32), np.ascontiguousarray(depths, np.float32))
    ntx = (int(width) + TILE - 1) // TILE
    nty = (int(height) + TILE - 1) // TILE
    n_chunks = max(1, min(numba.get_num_threads(), order.shape[0] // 4096 + 1))
    # the tile lists' size is known now, before they are allocated: refuse what cannot fit
    check_tile_lists(_count_pairs(rects), width, height, n_chunks)
    offsets, ids = _fill_bins(order, rects, ntx, ntx * nty, n_chunks)
    return TileBins(offsets, ids, packed, int(width), int(height))
