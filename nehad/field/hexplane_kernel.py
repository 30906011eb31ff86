"""The hex-plane lookup (docs/design.md section 4.1) and its backward as Numba passes, for training
on the CPU (issue 27; `HexPlane`'s grid_sample path is the reference and the GPU path).

For a point u = (x, y, z, t') and each scale, f_c = prod_k s_k,c with s_k the bilinear sample of
plane k (align_corners=True, border padding: the pixel coordinate is clamped to the plane, and a
clamped coordinate passes no gradient, as grid_sample's). The planes are read channel-last
((H, W, C) tables, one C-vector per texel), so a tap is one contiguous read. HexPlane stores
its planes channel-last (torch.channels_last: shape (1, C, H, W), memory (H, W, C)), so the
tables are a plain copy of the planes and the planes' gradients are views of the kernel's
gradient tables (a plane in the contiguous layout is reordered both ways).

Backward, with g = dL/df of one scale:

- dL/ds_k,c = g_c prod_{j != k} s_j,c (per point and channel, the points and their upstream
  rows gathered into the lookup's spatial order);
- dL/dplane_k: each corner of each point's cell gets its bilinear weight times dL/ds_k. With
  no more threads than scales, each scale is one task that puts dL/ds_k onto its own planes
  as it computes it (`_grads_by_scale`); else dL/ds_k is written out by a pass over the
  points (`_point_grads`) and a pass with one plane per task adds it up (`_plane_grads`), so
  that no two tasks write the same memory either way;
- dL/du along the plane's two axes: sum_c dL/ds_k,c times the sample's slope in that axis
  (the difference of the neighbouring texels), times 0.5 (res - 1) for the [-1, 1] scaling;
  along t only when the caller's time needs a gradient (`hexplane_lookup`'s `time_grad`: in
  training it needs none, and the three space-time planes' sums along t were a quarter of
  the slope sums, docs/performance.md).

Points whose upstream gradient is zero (Gaussians no pixel of the view sees) are left out of
the backward: they would add zeros to the planes' gradients and get a zero gradient themselves.

The spatial planes' total variation (`plane_tv`, the regulariser of docs/design.md section 5:
2 (mean dH^2 + mean dW^2) of a (1, C, H, W) plane) is one pass that writes its value and its
gradient together, dTV/dp[y, x] = (4 / n_H) (dH[y-1] - dH[y]) + (4 / n_W) (dW[x-1] - dW[x])
(a difference that falls outside the plane counts 0), where torch's autograd makes some ten
passes over the planes for it. The space-time planes' two regularisers, the mean squared second
difference along t and mean |1 - p| (`time_regularisers`), are one such pass as well.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from nehad.field.hnn_kernels import live_rows
from nehad.runtime.raster.intrinsics import EXACT_FASTMATH, fma32

_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
_HALF = np.float32(0.5)


@numba.njit(inline="always")
def _cell(coord, size):
    """(index of the cell's first texel, fraction, d pixel / d coord or 0 where clamped)."""
    slope = _HALF * np.float32(size - 1)
    p = fma32(coord, slope, slope)  # (coord + 1) slope, rounded once: the pixel to 1/2 ulp
    if p <= _ZERO:
        p = _ZERO
        slope = _ZERO
    elif p >= np.float32(size - 1):
        p = np.float32(size - 1)
        slope = _ZERO
    i0 = min(int(np.floor(p)), max(size - 2, 0))
    return i0, p - np.float32(i0), slope


@numba.njit(inline="always")
def _corners(u, n, p, k, offsets, heights, widths, axis_a, axis_b, channels):
    """Where point n reads plane p (plane k of its scale): the table offset of its cell's first
    texel, the offsets of the right and lower neighbours, the fractions and d pixel / d coord."""
    h, w = heights[p], widths[p]
    x0, fx, slope_x = _cell(u[n, axis_a[k]], w)
    y0, fy, slope_y = _cell(u[n, axis_b[k]], h)
    dx = channels if w > 1 else 0
    dy = w * channels if h > 1 else 0
    return offsets[p] + (y0 * w + x0) * channels, dx, dy, fx, fy, slope_x, slope_y


@numba.njit(inline="always")
def _bilinear(a, b, d, e, fx, fy):
    """The bilinear sample of texels a (corner), b (right), d (below), e (below right)."""
    top = fma32(fx, b - a, a)
    return fma32(fy, fma32(fx, e - d, d) - top, top)


@numba.njit(inline="always")
def _spread(grad_tables, base, dx, dy, fx, fy, gk, channels):
    """A point's dL/ds_k (gk) onto its cell's four texels, each with its bilinear weight."""
    w00 = (_ONE - fx) * (_ONE - fy)
    w01 = fx * (_ONE - fy)
    w10 = (_ONE - fx) * fy
    w11 = fx * fy
    g00 = grad_tables[base:base + channels]
    for c in range(channels):
        g00[c] = fma32(w00, gk[c], g00[c])
    g01 = grad_tables[base + dx:base + dx + channels]
    for c in range(channels):
        g01[c] = fma32(w01, gk[c], g01[c])
    g10 = grad_tables[base + dy:base + dy + channels]
    for c in range(channels):
        g10[c] = fma32(w10, gk[c], g10[c])
    g11 = grad_tables[base + dy + dx:base + dy + dx + channels]
    for c in range(channels):
        g11[c] = fma32(w11, gk[c], g11[c])


#: Partial sums of a slope sum (`_slope_sum`): a vector of float32s.
_LANES = 8


@numba.njit(inline="always")
def _slope_sum(gk, slope, channels):
    """sum_c gk_c slope_c: dL/d pixel along one of a plane's axes. Channel c is added into
    partial sum c % 8 (an order fixed by the code), the eight are then summed pairwise, and the
    channels past the last multiple of 8 are added one by one at the end. The partial sums are
    eight local variables: kept in registers, the slope sums took 90 ns a point's six planes
    where the same sums through a scratch array took 120 (docs/performance.md)."""
    p0 = p1 = p2 = p3 = p4 = p5 = p6 = p7 = _ZERO
    full = channels - channels % _LANES
    for c0 in range(0, full, _LANES):
        g = gk[c0:c0 + _LANES]
        v = slope[c0:c0 + _LANES]
        p0 = fma32(g[0], v[0], p0)
        p1 = fma32(g[1], v[1], p1)
        p2 = fma32(g[2], v[2], p2)
        p3 = fma32(g[3], v[3], p3)
        p4 = fma32(g[4], v[4], p4)
        p5 = fma32(g[5], v[5], p5)
        p6 = fma32(g[6], v[6], p6)
        p7 = fma32(g[7], v[7], p7)
    total = ((p0 + p4) + (p2 + p6)) + ((p1 + p5) + (p3 + p7))
    for c in range(full, channels):
        total = fma32(gk[c], slope[c], total)
    return total


@numba.njit(fastmath=EXACT_FASTMATH, cache=True)
def _forward_points(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
                    out, order, start, stop):
    """out's rows order[start:stop] (u in the lookup's spatial order: u[i] is point order[i];
    out in the points' own order), one plane after the other: each plane's texels are then
    read as one stream in the points' spatial order, which the hardware prefetcher follows,
    where the twelve planes read point by point were twelve streams at once (a step's lookup
    finds the planes out of the cache: 7000 points, 1 thread, after the cache was flushed,
    1.9-2.1 ms against 3.8-8.1; the same when the planes are cached). The same products in
    the same order (the first plane's sample is assigned, not multiplied into 1)."""
    for s in range(n_scales):
        for k in range(6):
            for n in range(start, stop):
                f = out[order[n], s * channels:(s + 1) * channels]
                base, dx, dy, fx, fy, _, _ = _corners(u, n, s * 6 + k, k, offsets, heights,
                                                      widths, axis_a, axis_b, channels)
                t00 = tables[base:base + channels]
                t01 = tables[base + dx:base + dx + channels]
                t10 = tables[base + dy:base + dy + channels]
                t11 = tables[base + dy + dx:base + dy + dx + channels]
                if k == 0:
                    for c in range(channels):
                        f[c] = _bilinear(t00[c], t01[c], t10[c], t11[c], fx, fy)
                else:
                    for c in range(channels):
                        f[c] *= _bilinear(t00[c], t01[c], t10[c], t11[c], fx, fy)


@numba.njit(parallel=True, cache=True)
def _forward(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales, channels, out,
             order, chunks):
    n = u.shape[0]
    for j in numba.prange(chunks):
        _forward_points(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
                        out, order, j * n // chunks, (j + 1) * n // chunks)


@numba.njit(parallel=True, cache=True)
def _take_rows(src, rows, dst):
    """dst[i] = src[rows[i]] (a gather into the spatial order)."""
    for i in numba.prange(rows.shape[0]):
        dst[i] = src[rows[i]]


@numba.njit(parallel=True, cache=True)
def _put_rows(src, rows, dst):
    """dst[rows[i]] = src[i] (a scatter back to the Gaussians' order)."""
    for i in numba.prange(rows.shape[0]):
        dst[rows[i]] = src[i]


@numba.njit(inline="always")
def _taps_with_slopes(u, n, s, tables, offsets, heights, widths, axis_a, axis_b, channels,
                      samples, sx, sy, slopes):
    """Point n's six samples of scale s (plane k at k * channels of `samples`), their slopes
    along the planes' two axes (`sx`, `sy`) and d pixel / d coord (`slopes`)."""
    for k in range(6):
        base, dx, dy, fx, fy, slope_x, slope_y = _corners(
            u, n, s * 6 + k, k, offsets, heights, widths, axis_a, axis_b, channels)
        slopes[k, 0] = slope_x
        slopes[k, 1] = slope_y
        o = k * channels
        t00 = tables[base:base + channels]
        t01 = tables[base + dx:base + dx + channels]
        t10 = tables[base + dy:base + dy + channels]
        t11 = tables[base + dy + dx:base + dy + dx + channels]
        sample = samples[o:o + channels]
        slope_a = sx[o:o + channels]
        slope_b = sy[o:o + channels]
        gy = _ONE - fy
        for c in range(channels):
            a, b, d, e = t00[c], t01[c], t10[c], t11[c]
            top = fma32(fx, b - a, a)
            bottom = fma32(fx, e - d, d)
            sample[c] = fma32(fy, bottom - top, top)
            slope_a[c] = fma32(gy, b - a, fy * (e - d))
            slope_b[c] = bottom - top


@numba.njit(inline="always")
def _products_of_the_others(g, samples, others, channels):
    """others[k] = g * prod_{j != k} samples[j] (plane k at k * channels): a prefix times a
    suffix product per channel, not thirty products. Channel by channel, the six planes in
    registers: plane by plane through a running row it took twice as long."""
    for c in range(channels):
        r = g[c]
        for k in range(6):  # others = g * prefix product
            others[k * channels + c] = r
            r *= samples[k * channels + c]
        r = _ONE
        for k in range(5, -1, -1):  # ... times the suffix product
            others[k * channels + c] *= r
            r *= samples[k * channels + c]


@numba.njit(fastmath=EXACT_FASTMATH, cache=True)
def _point_grads_range(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
                       wanted, grad_out, grad_samples, grad_u, start, stop):
    """dL/ds_k (into `grad_samples`) and dL/du per scale (grad_u (S, points, 4)) of the points
    start:stop, with u, grad_out and grad_u in the lookup's spatial order (read in the
    Gaussians' order, each point's upstream row was a cache miss the long loop body could not
    hide: 10k points, 1 thread, 5.8 -> 3.2 ms). The scratch rows are flat (plane k at
    k * channels), and every loop over the channels runs over slices (views of one row), which
    LLVM vectorises: indexed through the whole arrays the same loops took twice as long (10k
    points, 2 threads: 4.9 -> 2.1-2.3 ms)."""
    samples = np.empty(6 * channels, np.float32)
    sx = np.empty(6 * channels, np.float32)  # d sample / d pixel x
    sy = np.empty(6 * channels, np.float32)
    others = np.empty(6 * channels, np.float32)  # prod_{j != k} s_j
    slopes = np.empty((6, 2), np.float32)
    for n in range(start, stop):
        for s in range(n_scales):
            _taps_with_slopes(u, n, s, tables, offsets, heights, widths, axis_a, axis_b,
                              channels, samples, sx, sy, slopes)
            _products_of_the_others(grad_out[n, s * channels:(s + 1) * channels], samples,
                                    others, channels)
            for k in range(6):
                o = k * channels
                other = others[o:o + channels]
                grad_samples[s * 6 + k, n] = other
                a = axis_a[k]
                b = axis_b[k]
                if wanted[a]:
                    ax = _slope_sum(other, sx[o:o + channels], channels)
                    grad_u[s, n, a] = fma32(ax, slopes[k, 0], grad_u[s, n, a])
                if wanted[b]:
                    ay = _slope_sum(other, sy[o:o + channels], channels)
                    grad_u[s, n, b] = fma32(ay, slopes[k, 1], grad_u[s, n, b])


@numba.njit(parallel=True, cache=True)
def _point_grads(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
                 wanted, grad_out, grad_samples, grad_u, chunks):
    n = u.shape[0]
    for j in numba.prange(chunks):
        _point_grads_range(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales,
                           channels, wanted, grad_out, grad_samples, grad_u, j * n // chunks,
                           (j + 1) * n // chunks)


@numba.njit(fastmath=EXACT_FASTMATH, cache=True)
def _scale_grads(u, tables, offsets, heights, widths, axis_a, axis_b, s, channels, wanted,
                 grad_out, grad_u, grad_tables):
    """Every point's dL/du share and the six planes' gradients of scale s in one pass (u and
    grad_out in the lookup's spatial order): a point's dL/ds_k goes straight onto its cell's
    four corners, so it is never written out and read back (`_grads_by_scale`)."""
    samples = np.empty(6 * channels, np.float32)
    sx = np.empty(6 * channels, np.float32)  # d sample / d pixel x
    sy = np.empty(6 * channels, np.float32)
    others = np.empty(6 * channels, np.float32)  # g prod_{j != k} s_j = dL/ds_k
    slopes = np.empty((6, 2), np.float32)
    for n in range(u.shape[0]):
        _taps_with_slopes(u, n, s, tables, offsets, heights, widths, axis_a, axis_b, channels,
                          samples, sx, sy, slopes)
        _products_of_the_others(grad_out[n, s * channels:(s + 1) * channels], samples, others,
                                channels)
        for k in range(6):
            o = k * channels
            other = others[o:o + channels]
            a = axis_a[k]
            b = axis_b[k]
            if wanted[a]:
                ax = _slope_sum(other, sx[o:o + channels], channels)
                grad_u[n, a] = fma32(ax, slopes[k, 0], grad_u[n, a])
            if wanted[b]:
                ay = _slope_sum(other, sy[o:o + channels], channels)
                grad_u[n, b] = fma32(ay, slopes[k, 1], grad_u[n, b])
            base, dx, dy, fx, fy, _, _ = _corners(u, n, s * 6 + k, k, offsets, heights, widths,
                                                  axis_a, axis_b, channels)
            _spread(grad_tables, base, dx, dy, fx, fy, other, channels)


@numba.njit(parallel=True, cache=True)
def _grads_by_scale(u, tables, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
                    wanted, grad_out, grad_u_scales, grad_tables):
    """`_scale_grads` of each scale as one task: a scale's planes belong to it alone, so no two
    tasks write the same memory (dL/du per scale, summed by the caller)."""
    for s in numba.prange(n_scales):
        _scale_grads(u, tables, offsets, heights, widths, axis_a, axis_b, s, channels, wanted,
                     grad_out, grad_u_scales[s], grad_tables)


@numba.njit(fastmath=EXACT_FASTMATH, cache=True)
def _scatter_plane(u, p, k, offsets, heights, widths, axis_a, axis_b, channels, grad_samples,
                   grad_tables):
    for n in range(u.shape[0]):
        base, dx, dy, fx, fy, _, _ = _corners(u, n, p, k, offsets, heights, widths, axis_a,
                                              axis_b, channels)
        _spread(grad_tables, base, dx, dy, fx, fy, grad_samples[p, n], channels)


@numba.njit(parallel=True, cache=True)
def _plane_grads(u, offsets, heights, widths, axis_a, axis_b, channels, grad_samples,
                 grad_tables):
    for p in numba.prange(offsets.shape[0] - 1):
        _scatter_plane(u, p, p % 6, offsets, heights, widths, axis_a, axis_b, channels,
                       grad_samples, grad_tables)


@numba.njit(parallel=True, cache=True)
def _to_channel_last(plane, out):
    """(C, H, W) -> (H, W, C) into `out` (flat), rows in parallel."""
    c, h, w = plane.shape
    for y in numba.prange(h):
        for x in range(w):
            base = (y * w + x) * c
            for k in range(c):
                out[base + k] = plane[k, y, x]


@numba.njit(parallel=True, cache=True)
def _to_channel_first(flat, out):
    """(H, W, C) flat -> (C, H, W) `out`."""
    c, h, w = out.shape
    for k in numba.prange(c):
        for y in range(h):
            for x in range(w):
                out[k, y, x] = flat[(y * w + x) * c + k]


@numba.njit(fastmath=True, cache=True)
def _tv_row(p, row, width, height, lag, wh, ww, grad):
    """TV terms of one row of a plane stored as `height` rows of `width` floats (the flat
    (H, W, C) of a channel-last plane: a row is y, neighbours along W are `lag` = C floats
    apart; or the flat (C, H, W): a row is (c, y), `lag` = 1): the sum of dH^2 between the row
    and the next, the sum of its dW^2, and its gradient entries (weights wh = 4 / n_H, ww =
    4 / n_W). The loops run over views of single rows, shifted views where they pair
    neighbours, and index them with the loop counter alone, so that they vectorise: indexed
    through the whole arrays they took 17 ns an element; with v[x - lag] in the loop, whose
    index Numba must check for wrap-around, 1 ns; as now, about 0.1 ns (docs/performance.md)."""
    y = row % height
    base = row * width
    v = p[base:base + width]
    g = grad[base:base + width]
    sum_w = 0.0
    pairs = max(width - lag, 0)
    ahead, behind = v[lag:lag + pairs], v[:pairs]
    for x in range(pairs):
        d = ahead[x] - behind[x]
        sum_w += d * d
    # the inner second differences through three shifted views (docstring)
    inner = max(width - 2 * lag, 0)
    centre, left, right = v[lag:lag + inner], v[:inner], v[2 * lag:2 * lag + inner]
    g_inner = g[lag:lag + inner]
    for x in range(inner):
        g_inner[x] = ww * (np.float32(2.0) * centre[x] - left[x] - right[x])
    if width > lag:
        for x in range(lag):
            g[x] = ww * (v[x] - v[x + lag])
            g[width - lag + x] = ww * (v[width - lag + x] - v[width - 2 * lag + x])
    else:
        for x in range(width):
            g[x] = _ZERO
    if y > 0:
        up = p[base - width:base]
        for x in range(width):
            g[x] += wh * (v[x] - up[x])
    sum_h = 0.0
    if y < height - 1:
        down = p[base + width:base + 2 * width]
        for x in range(width):
            d = down[x] - v[x]
            sum_h += d * d
            g[x] -= wh * d
    return sum_h, sum_w


@numba.njit(parallel=True, cache=True)
def _plane_tv(p, rows, height, width, lag, n_h, n_w, grad, sums):
    wh = np.float32(4.0 / max(n_h, 1))
    ww = np.float32(4.0 / max(n_w, 1))
    for row in numba.prange(rows):
        sh, sw = _tv_row(p, row, width, height, lag, wh, ww, grad)
        sums[row, 0] = sh
        sums[row, 1] = sw
    return 2.0 * (sums[:, 0].sum() / max(n_h, 1) + sums[:, 1].sum() / max(n_w, 1))


def _channel_last_plane(flat: np.ndarray, shape) -> torch.Tensor:
    """A flat (H, W, C) array viewed, without a copy, as a (1, C, H, W) tensor in channel-last
    memory (HexPlane's layout)."""
    _, c, h, w = shape
    return torch.from_numpy(flat.reshape(h, w, c)).permute(2, 0, 1)[None]


def _rows_of(plane: torch.Tensor):
    """(flat float32 array, rows, rows per (c) block, row length, lag along W, and a function
    that views a flat array of the same layout as a tensor shaped like `plane`) for a
    (1, C, H, W) plane stored channel-last (the layout HexPlane keeps) or contiguous."""
    _, c, h, w = plane.shape
    data = plane.detach()[0]
    if plane.is_contiguous(memory_format=torch.channels_last):
        flat = data.permute(1, 2, 0).numpy().reshape(-1)  # (H, W, C), no copy
        return flat, h, h, w * c, c, lambda a: _channel_last_plane(a, plane.shape)
    flat = np.ascontiguousarray(data.numpy(), np.float32).reshape(-1)
    return flat, c * h, h, w, 1, lambda a: torch.from_numpy(a.reshape(1, c, h, w))


def tv_pass(plane: torch.Tensor, grad: np.ndarray):
    """(the K-Planes total variation of a (1, C, H, W) float32 plane, a function viewing a flat
    array of the plane's layout as a tensor shaped like it), the gradient written into `grad`
    (plane.numel() floats in the plane's layout, `_rows_of`): `PlaneTV`'s one Numba pass."""
    _, c, h, w = plane.shape
    flat, rows, height, width, lag, as_plane = _rows_of(plane)
    value = _plane_tv(flat, rows, height, width, lag, c * (h - 1) * w, c * h * (w - 1), grad,
                      np.empty((rows, 2), np.float64))
    return value, as_plane


def time_pass(plane: torch.Tensor, grad_second: np.ndarray, grad_l1: np.ndarray):
    """(mean squared second difference along t, mean |1 - p|, the viewing function of
    `tv_pass`) of a (1, C, T, W) float32 space-time plane, their gradients written into
    `grad_second` and `grad_l1` (the plane's layout): `TimeRegularisers`' one Numba pass."""
    _, c, h, w = plane.shape
    flat, rows, height, width, _, as_plane = _rows_of(plane)
    second, l1 = _time_regularisers(flat, rows, height, width, c * max(h - 2, 0) * w, c * h * w,
                                    grad_second, grad_l1, np.empty((rows, 2), np.float64))
    return second, l1, as_plane


class PlaneTV(torch.autograd.Function):
    """K-Planes total variation 2 (mean dH^2 + mean dW^2) of a (1, C, H, W) float32 plane
    (nehad.field.hexplane._tv) and its gradient in one Numba pass (module docstring)."""

    @staticmethod
    def forward(ctx, plane):
        grad = np.empty(plane.numel(), np.float32)
        value, as_plane = tv_pass(plane, grad)
        ctx.grad = as_plane(grad)
        return plane.new_tensor(value)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_value):
        grad, ctx.grad = ctx.grad, None  # the forward's own array, scaled in place: no copy
        return grad.mul_(grad_value)


def plane_tv(plane: torch.Tensor) -> torch.Tensor:
    """`PlaneTV` of a (1, C, H, W) plane."""
    return PlaneTV.apply(plane)


@numba.njit(fastmath=True, cache=True)
def _time_row(p, row, width, height, w2, w1, grad_second, grad_l1):
    """The space-time regularisers' terms of one row of a plane stored as rows (`_tv_row`; H
    is t): the squared second differences dd(y) = p[y + 2] - 2 p[y + 1] + p[y] that start
    at it and |1 - p|, summed over the row, and their gradients (weights w2 = 2 / n_second,
    w1 = 1 / n_all); the gradient of row y gathers dd(y) - 2 dd(y - 1) + dd(y - 2). Loops over
    row views, as `_tv_row`."""
    y = row % height
    base = row * width
    v = p[base:base + width]
    g2 = grad_second[base:base + width]
    g1 = grad_l1[base:base + width]
    for x in range(width):
        g2[x] = _ZERO
    sum_dd = 0.0
    for lag in range(3):
        h = y - lag
        if h < 0 or h + 2 >= height:
            continue
        a = p[base - lag * width:base - lag * width + width]
        b = p[base - lag * width + width:base - lag * width + 2 * width]
        c = p[base - lag * width + 2 * width:base - lag * width + 3 * width]
        coef = w2 * (np.float32(-2.0) if lag == 1 else _ONE)
        if lag == 0:  # the row's own second differences: also summed for the value
            for x in range(width):
                dd = c[x] - np.float32(2.0) * b[x] + a[x]
                g2[x] += coef * dd
                sum_dd += dd * dd
        else:
            for x in range(width):
                g2[x] += coef * (c[x] - np.float32(2.0) * b[x] + a[x])
    sum_l1 = 0.0
    for x in range(width):
        r = _ONE - v[x]
        sum_l1 += abs(r)
        g1[x] = w1 * (np.float32(-1.0) if r > _ZERO else (_ONE if r < _ZERO else _ZERO))
    return sum_dd, sum_l1


@numba.njit(parallel=True, cache=True)
def _time_regularisers(p, rows, height, width, n_second, n_all, grad_second, grad_l1, sums):
    w2 = np.float32(2.0 / max(n_second, 1))
    w1 = np.float32(1.0 / n_all)
    for row in numba.prange(rows):
        sd, sl = _time_row(p, row, width, height, w2, w1, grad_second, grad_l1)
        sums[row, 0] = sd
        sums[row, 1] = sl
    return sums[:, 0].sum() / max(n_second, 1), sums[:, 1].sum() / n_all


class TimeRegularisers(torch.autograd.Function):
    """(mean squared second difference along t, mean |1 - p|) of a (1, C, T, W) float32
    space-time plane (nehad.field.hexplane._second_order and HexPlane.time_l1's term) and their
    gradients in one Numba pass."""

    @staticmethod
    def forward(ctx, plane):
        grads = np.empty((2, plane.numel()), np.float32)
        second, l1, as_plane = time_pass(plane, grads[0], grads[1])
        ctx.grads = (as_plane(grads[0]), as_plane(grads[1]))
        return plane.new_tensor(second), plane.new_tensor(l1)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_second, grad_l1):
        (second, l1), ctx.grads = ctx.grads, None  # the forward's own arrays: summed in place
        return second.mul_(grad_second).add_(l1.mul_(grad_l1))


def time_regularisers(plane: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`TimeRegularisers` of a (1, C, T, W) plane."""
    return TimeRegularisers.apply(plane)


@numba.njit(cache=True)
def _cell_sort(u, cells):
    """The stable counting sort of `_spatial_order`: point indices by their cell's key."""
    n = u.shape[0]
    keys = np.empty(n, np.int64)
    counts = np.zeros(cells * cells * cells + 1, np.int64)
    top = np.float32(cells - 1)
    for i in range(n):
        key = 0
        for a in range(3):
            q = (u[i, a] + _ONE) * np.float32(0.5 * cells)
            if not q >= _ZERO:  # below the box (a NaN coordinate is replaced by 0 before
                q = _ZERO       # the kernels run: HexPlaneLookup.forward)
            elif q > top:
                q = top
            key = key * cells + int(q)
        keys[i] = key
        counts[key + 1] += 1
    for k in range(cells * cells * cells):
        counts[k + 1] += counts[k]
    order = np.empty(n, np.int64)
    for i in range(n):
        order[counts[keys[i]]] = i
        counts[keys[i]] += 1
    return order


def _spatial_order(u: np.ndarray, cells: int = 32) -> np.ndarray:
    """The points in the order of a coarse grid over [-1, 1]^3 (x-major cells of 2 / `cells`,
    in each cell the points' own order): neighbouring points read neighbouring texels, so the
    table reads hit the cache (in the Gaussians' own order every tap was a cache miss). A
    counting sort (0.04 ms for 10k points, where numpy's argsort of the keys took 0.5)."""
    return _cell_sort(u, cells)


def _chunks(n: int) -> int:
    """Point ranges of the parallel loops: many per thread, so the threads stay balanced."""
    return max(1, min(n, 64 * numba.get_num_threads()))


def backward_by_scale(n_scales: int) -> bool:
    """Whether the lookup's backward runs one task per scale (`_grads_by_scale`: each point's
    dL/ds_k goes onto the planes as it is computed) rather than a pass over the points and one
    over the planes (`_point_grads`, `_plane_grads`: dL/ds_k written out, (12, rows, 32) floats,
    and read back). Per scale while there are no more threads than scales, the case of the
    2-core machines this project trains on (docs/performance.md); with more threads the two
    passes keep them all busy. Both compute the same sums in the same order (dL/du per scale,
    each texel's shares in the points' order), so training does not depend on the threads."""
    return numba.get_num_threads() <= n_scales


def _shared_table(planes, offsets):
    """The planes' one flat (H, W, C)-per-plane table without a copy, when they are channel-last
    views of one buffer, one after the other (as HexPlane allocates them); else None (planes
    converted with `.to()`, loaded on their own, ...)."""
    first = planes[0]
    base, ptr = first.storage_offset(), first.untyped_storage().data_ptr()
    for p, lo in zip(planes, offsets[:-1]):
        if (p.dtype != torch.float32 or not p.is_contiguous(memory_format=torch.channels_last)
                or p.untyped_storage().data_ptr() != ptr or p.storage_offset() != base + lo):
            return None
    return torch.as_strided(first.detach(), (int(offsets[-1]),), (1,), base).numpy()


class HexPlaneLookup(torch.autograd.Function):
    """features (N, S C) = the product over planes of bilinear samples (module docstring), for
    u (N, 4) = (x, y, z, t') and the S x 6 planes (1, C, H, W) in HexPlane's order. With
    `time_grad` False, dL/du is not computed along t (returned 0 there: for a time column that
    requires no gradient). With `into_grad`, the backward adds the planes' gradients straight
    into their `.grad` when those are views of one flat array laid out as the planes' table
    (as `nehad.optim.TrainingAdam.zero_grad` installs them) and returns none for them
    (`gradients_into`); otherwise it returns them, as autograd expects."""

    @staticmethod
    def forward(ctx, u, axes, time_grad, into_grad, *planes):
        channels = planes[0].shape[1]
        n_scales = len(planes) // 6
        sizes = [p.numel() for p in planes]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        flat = _shared_table(planes, offsets)
        if flat is None:  # planes of their own: gathered into one table
            flat = np.empty(int(offsets[-1]), np.float32)
            for p, lo, hi in zip(planes, offsets[:-1], offsets[1:]):  # each plane as (H, W, C)
                if p.is_contiguous(memory_format=torch.channels_last):
                    flat[lo:hi] = p.detach()[0].permute(1, 2, 0).numpy().reshape(-1)
                else:
                    _to_channel_last(np.ascontiguousarray(p.detach()[0].numpy()), flat[lo:hi])
        heights = np.array([p.shape[2] for p in planes], np.int64)
        widths = np.array([p.shape[3] for p in planes], np.int64)
        axis_a = np.array([a for a, _ in axes], np.int64)
        axis_b = np.array([b for _, b in axes], np.int64)
        un = np.ascontiguousarray(u.detach().numpy(), np.float32)
        if not np.isfinite(un).all():  # a diverged step (the trainer stops on its NaN loss):
            # the kernels index the tables with the coordinates, so no NaN or inf may reach them
            un = np.nan_to_num(un, nan=0.0, posinf=1.0, neginf=-1.0)
        order = _spatial_order(un)
        sorted_u = np.empty_like(un)  # the kernels work in the spatial order
        _take_rows(un, order, sorted_u)
        out = np.empty((un.shape[0], n_scales * channels), np.float32)
        _forward(sorted_u, flat, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
                 out, order, _chunks(len(un)))
        ctx.saved = (sorted_u, flat, offsets, heights, widths, axis_a, axis_b, n_scales,
                     channels, [tuple(p.shape) for p in planes], order,
                     [p.is_contiguous(memory_format=torch.channels_last) for p in planes])
        ctx.time_grad = bool(time_grad)
        ctx.planes = planes if into_grad else None  # their `.grad` is read at the backward
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        (sorted_u, flat, offsets, heights, widths, axis_a, axis_b, n_scales, channels,
         shapes, order, channel_last) = ctx.saved
        g = np.ascontiguousarray(grad_out.detach().numpy(), np.float32)
        n = sorted_u.shape[0]
        # the points with a gradient only (a point no pixel of the view sees has none, and would
        # add zeros everywhere: about half of a MuJoCo scene's, docs/performance.md)
        live = np.empty(n, np.bool_)
        live_rows(g[None], live, _chunks(n))
        active = live[order]
        if not active.all():
            kept = np.flatnonzero(active)
            order, sorted_u = order[kept], sorted_u[kept]
        m = len(order)
        sorted_g = np.empty((m, g.shape[1]), np.float32)
        _take_rows(g, order, sorted_g)
        planes_wanted = any(ctx.needs_input_grad[4:])  # none: a Jacobian by the points
        sink = (gradients_into(ctx.planes, offsets) if ctx.planes is not None and planes_wanted
                else None)
        grad_tables = sink if sink is not None else np.zeros_like(flat)
        space = ctx.needs_input_grad[0]  # dL/du along x, y, z; along t only if asked
        wanted = np.array([space, space, space, space and ctx.time_grad], np.bool_)
        # dL/du per scale, summed over the scales at the end: the same sums either way below
        by_scale = np.zeros((n_scales, m, 4), np.float32)
        # per scale, the planes' gradients are made whether wanted or not: the pass over the
        # points alone (`_point_grads`) is another kernel to compile, 8 s on a first run
        if backward_by_scale(n_scales):
            _grads_by_scale(sorted_u, flat, offsets, heights, widths, axis_a, axis_b, n_scales,
                            channels, wanted, sorted_g, by_scale, grad_tables)
        else:
            # plane-major, in the spatial order: each plane's scatter then reads it front to back
            grad_samples = np.empty((n_scales * 6, m, channels), np.float32)
            _point_grads(sorted_u, flat, offsets, heights, widths, axis_a, axis_b, n_scales,
                         channels, wanted, sorted_g, grad_samples, by_scale, _chunks(m))
            if planes_wanted:
                _plane_grads(sorted_u, offsets, heights, widths, axis_a, axis_b, channels,
                             grad_samples, grad_tables)
        sorted_grad_u = by_scale.sum(axis=0)
        grad_u = np.zeros((n, 4), np.float32)
        _put_rows(sorted_grad_u, order, grad_u)
        if sink is not None or not planes_wanted:
            if sink is not None:  # added into the planes' .grad: tell autograd they changed
                torch.autograd.graph.increment_version(ctx.planes[0].grad)
            return (torch.from_numpy(grad_u) if space else None, None, None, None,
                    *[None] * len(shapes))
        plane_grads = []
        for p, (shape, last) in enumerate(zip(shapes, channel_last)):
            table = grad_tables[offsets[p]:offsets[p + 1]]
            if last:  # the gradient in the plane's own layout, no copy
                plane_grads.append(_channel_last_plane(table, shape))
                continue
            out = np.empty(shape[1:], np.float32)
            _to_channel_first(table, out)
            plane_grads.append(torch.from_numpy(out).reshape(shape))
        return (torch.from_numpy(grad_u) if space else None, None, None, None, *plane_grads)


def gradients_into(planes, offsets):
    """The flat float32 array the planes' `.grad` are channel-last views of, one after the
    other at `offsets` (the layout of the lookup's table), or None (a plane without `.grad`,
    gradients of their own): where the lookup's backward may add its gradients in place."""
    grads = [p.grad for p in planes]
    if any(g is None for g in grads):
        return None
    return _shared_table(grads, offsets)


def hexplane_lookup(u: torch.Tensor, planes, axes, time_grad: bool = True,
                    into_grad: bool = False) -> torch.Tensor:
    """`HexPlaneLookup` of points u (N, 4) and the planes (flat list, scale-major); with
    `time_grad` False no dL/du along t (the caller's time column needs none); with `into_grad`
    the planes' gradients go straight into their `.grad` where it is one flat array (for a
    `.backward()` only: a `torch.autograd.grad` would find them there, not in its result)."""
    return HexPlaneLookup.apply(u, tuple(axes), time_grad, into_grad, *planes)


__all__ = ["HexPlaneLookup", "PlaneTV", "TimeRegularisers", "hexplane_lookup", "plane_tv",
           "time_regularisers"]
