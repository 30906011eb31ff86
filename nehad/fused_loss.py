"""The photometric loss (1 - w) L1 + w (1 - SSIM) of one (H, W, C) image with its gradient, as
two Numba passes (issue 27; the torch version in :mod:`nehad.losses` is the reference).

SSIM is 3DGS's: per channel, 11-tap Gaussian window (sigma 1.5), zero padding, 'same' size, mean
over every pixel and channel (docs/design.md section 9). With the five blurred moments
mu_x = G*x, mu_y = G*y, e_xx = G*x^2, e_yy = G*y^2, e_xy = G*xy at a pixel p,

    s = (2 mu_x mu_y + C1) (2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1) (s_xx + s_yy + C2))

(s_xx = e_xx - mu_x^2, ...). s depends on x only through mu_x, e_xx and e_xy, and the window G is
symmetric with zero padding (its own adjoint), so

    d(sum_p s_p) / dx_q = (G*A)_q + 2 x_q (G*B)_q + y_q (G*C)_q,
    A = ds/dmu_x = 2 (mu_y (N2 - N1) - s mu_x (D2 - D1)) / (D1 D2),  B = ds/de_xx = -s / D2,
    C = ds/de_xy = 2 N1 / (D1 D2)

(N1, N2 the numerator's factors, D1, D2 the denominator's). The first pass blurs the five
moments of each output row (vertical taps, then horizontal), evaluates s, A, B, C there and keeps
A, B, C; the second blurs A, B, C the same way and writes the gradient. Both run in parallel over
rows; nothing of the size of the image is built besides A, B, C and the gradient.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from nehad.blur import gaussian_taps

_C1 = np.float32(0.01 ** 2)
_C2 = np.float32(0.03 ** 2)
_TWO = np.float32(2.0)


@numba.njit(inline="always")
def _add_scaled(dst, a, src):
    """dst += a src (one array written per loop: LLVM vectorises a loop only when its run-time
    alias checks stay few)."""
    for i in range(dst.shape[0]):
        dst[i] += a * src[i]


@numba.njit(inline="always")
def _add_scaled_product(dst, a, src1, src2):
    """dst += a src1 src2."""
    for i in range(dst.shape[0]):
        dst[i] += a * src1[i] * src2[i]


@numba.njit(inline="always")
def _horizontal(padded, taps, out):
    """out = the horizontal taps over `padded` (a row with len(taps) // 2 zeros at each end)."""
    for i in range(out.shape[0]):
        out[i] = 0.0
    for t in range(taps.shape[0]):
        _add_scaled(out, taps[t], padded[t:t + out.shape[0]])


@numba.njit(inline="always")
def _vertical_moments(x, y, taps, c, row, bx_in, by_in, bxx_in, byy_in, bxy_in):
    """The vertical taps of the five moments x, y, x^2, y^2, xy of channel `c` around row `row`
    into the inner parts of the padded row buffers (zeroed first; rows outside the image add
    nothing)."""
    h, w = x.shape[1], x.shape[2]
    k = taps.shape[0]
    r = k // 2
    for i in range(w):
        bx_in[i] = 0.0
        by_in[i] = 0.0
        bxx_in[i] = 0.0
        byy_in[i] = 0.0
        bxy_in[i] = 0.0
    for t in range(k):
        src = row + t - r
        if src < 0 or src >= h:
            continue
        wt = taps[t]
        xr = x[c, src]
        yr = y[c, src]
        _add_scaled(bx_in, wt, xr)
        _add_scaled(by_in, wt, yr)
        _add_scaled_product(bxx_in, wt, xr, xr)
        _add_scaled_product(byy_in, wt, yr, yr)
        _add_scaled_product(bxy_in, wt, xr, yr)


@numba.njit(inline="always")
def _ssim_coefficients(mx, my, exx, eyy, exy, xr, yr, a_row, b_row, c_row, s_sum, l1_sum):
    """s and A, B, C (written to `a_row`, `b_row`, `c_row`) at every pixel of one row of one
    channel from its blurred moments; returns `s_sum` and `l1_sum` with the row's s and
    |x - y| added."""
    for i in range(mx.shape[0]):
        ux = mx[i]
        uy = my[i]
        n1 = _TWO * ux * uy + _C1
        n2 = _TWO * (exy[i] - ux * uy) + _C2
        d1 = ux * ux + uy * uy + _C1
        d2 = (exx[i] - ux * ux) + (eyy[i] - uy * uy) + _C2
        inv = np.float32(1.0) / (d1 * d2)
        s = n1 * n2 * inv
        s_sum += s
        a_row[i] = _TWO * (uy * (n2 - n1) - s * ux * (d2 - d1)) * inv
        b_row[i] = -s / d2
        c_row[i] = _TWO * n1 * inv
        l1_sum += abs(xr[i] - yr[i])
    return s_sum, l1_sum


@numba.njit(fastmath=True, cache=True)
def _ssim_row(x, y, taps, coef_a, coef_b, coef_c, row):
    """Row `row` of the first pass (see `_ssim_rows`); returns its sums of s and |x - y|."""
    nc, h, w = x.shape
    k = taps.shape[0]
    r = k // 2
    bx = np.zeros(w + 2 * r, np.float32)
    by = np.zeros(w + 2 * r, np.float32)
    bxx = np.zeros(w + 2 * r, np.float32)
    byy = np.zeros(w + 2 * r, np.float32)
    bxy = np.zeros(w + 2 * r, np.float32)
    # views with non-negative loop-counter indices (a negative-index check would stop LLVM
    # from vectorising the loops)
    bx_in, by_in, bxx_in = bx[r:r + w], by[r:r + w], bxx[r:r + w]
    byy_in, bxy_in = byy[r:r + w], bxy[r:r + w]
    mx = np.empty(w, np.float32)
    my = np.empty(w, np.float32)
    exx = np.empty(w, np.float32)
    eyy = np.empty(w, np.float32)
    exy = np.empty(w, np.float32)
    s_sum = 0.0
    l1_sum = 0.0
    for c in range(nc):
        _vertical_moments(x, y, taps, c, row, bx_in, by_in, bxx_in, byy_in, bxy_in)
        _horizontal(bx, taps, mx)  # the pads stay zero
        _horizontal(by, taps, my)
        _horizontal(bxx, taps, exx)
        _horizontal(byy, taps, eyy)
        _horizontal(bxy, taps, exy)
        s_sum, l1_sum = _ssim_coefficients(mx, my, exx, eyy, exy, x[c, row], y[c, row],
                                           coef_a[c, row], coef_b[c, row], coef_c[c, row],
                                           s_sum, l1_sum)
    return s_sum, l1_sum


@numba.njit(parallel=True, fastmath=True, cache=True)
def _ssim_rows(x, y, taps, coef_a, coef_b, coef_c, s_rows, l1_rows):
    """x, y: (C, H, W) float32. Writes A, B, C (C, H, W) and, per row, the sums of s and |x - y|
    over the row's pixels and channels (float64, summed outside: no shared accumulator). The row
    bodies are functions of their own: Numba vectorises the inner loops of a called function but
    not those written inside a prange body (measured: 14x slower there)."""
    h = x.shape[1]
    for row in numba.prange(h):
        s_rows[row], l1_rows[row] = _ssim_row(x, y, taps, coef_a, coef_b, coef_c, row)


@numba.njit(fastmath=True, cache=True)
def _ssim_grad_row(x, y, coef_a, coef_b, coef_c, taps, w_ssim, w_l1, grad, row):
    """Row `row` of the second pass (see `_ssim_grad_rows`)."""
    nc, h, w = x.shape
    k = taps.shape[0]
    r = k // 2
    ba = np.zeros(w + 2 * r, np.float32)
    bb = np.zeros(w + 2 * r, np.float32)
    bc = np.zeros(w + 2 * r, np.float32)
    ba_in, bb_in, bc_in = ba[r:r + w], bb[r:r + w], bc[r:r + w]
    ga = np.empty(w, np.float32)
    gb = np.empty(w, np.float32)
    gc = np.empty(w, np.float32)
    for c in range(nc):
        for i in range(w):
            ba_in[i] = 0.0
            bb_in[i] = 0.0
            bc_in[i] = 0.0
        for t in range(k):
            src = row + t - r
            if src < 0 or src >= h:
                continue
            wt = taps[t]
            _add_scaled(ba_in, wt, coef_a[c, src])
            _add_scaled(bb_in, wt, coef_b[c, src])
            _add_scaled(bc_in, wt, coef_c[c, src])
        _horizontal(ba, taps, ga)
        _horizontal(bb, taps, gb)
        _horizontal(bc, taps, gc)
        xr = x[c, row]
        yr = y[c, row]
        gr = grad[c, row]
        for i in range(w):
            gr[i] = (w_l1 * np.sign(xr[i] - yr[i])
                     + w_ssim * (ga[i] + _TWO * xr[i] * gb[i] + yr[i] * gc[i]))


@numba.njit(parallel=True, fastmath=True, cache=True)
def _ssim_grad_rows(x, y, coef_a, coef_b, coef_c, taps, w_ssim, w_l1, grad):
    """grad (C, H, W) = w_l1 sign(x - y) + w_ssim ((G*A) + 2 x (G*B) + y (G*C))."""
    for row in numba.prange(x.shape[1]):
        _ssim_grad_row(x, y, coef_a, coef_b, coef_c, taps, w_ssim, w_l1, grad, row)


_WORKSPACE: dict = {}


def _workspace(nc: int, h: int, w: int) -> np.ndarray:
    """The (3, C, H, W) buffer of A, B, C, kept between calls of one image size: a fresh one costs
    its page faults at every step (about as much as a pass, measured at 400x400)."""
    key = (nc, h, w)
    if key not in _WORKSPACE:
        _WORKSPACE.clear()
        _WORKSPACE[key] = np.empty((3, nc, h, w), np.float32)
    return _WORKSPACE[key]


def photometric_loss_and_grad(img: np.ndarray, ref: np.ndarray, ssim_weight: float = 0.2,
                              window: int = 11, need_grad: bool = True):
    """Loss (1 - w) mean|img - ref| + w (1 - mean SSIM) of two (H, W, C) float32 images, and its
    gradient with respect to `img` ((H, W, C) float32, or None when `need_grad` is false)."""
    h, w, nc = img.shape
    x = np.ascontiguousarray(np.moveaxis(np.asarray(img, np.float32), 2, 0))
    y = np.ascontiguousarray(np.moveaxis(np.asarray(ref, np.float32), 2, 0))
    taps = gaussian_taps(window, 1.5)
    coef = _workspace(nc, h, w)
    s_rows = np.empty(h, np.float64)
    l1_rows = np.empty(h, np.float64)
    _ssim_rows(x, y, taps, coef[0], coef[1], coef[2], s_rows, l1_rows)
    count = float(h * w * nc)
    loss = ((1.0 - ssim_weight) * l1_rows.sum() / count
            + ssim_weight * (1.0 - s_rows.sum() / count))
    if not need_grad:
        return loss, None
    grad = np.empty((nc, h, w), np.float32)
    _ssim_grad_rows(x, y, coef[0], coef[1], coef[2], taps, np.float32(-ssim_weight / count),
                    np.float32((1.0 - ssim_weight) / count), grad)
    return loss, np.moveaxis(grad, 0, 2)  # (H, W, C), a strided view


class _FusedPhotometricLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img, ref, ssim_weight):
        loss, grad = photometric_loss_and_grad(img.detach().numpy(), ref.detach().numpy(),
                                               ssim_weight, need_grad=ctx.needs_input_grad[0])
        ctx.grad = None if grad is None else torch.from_numpy(grad)
        return torch.tensor(loss, dtype=img.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        return grad_out * ctx.grad, None, None


def fused_photometric_loss(img: torch.Tensor, ref: torch.Tensor, ssim_weight: float = 0.2):
    """`nehad.losses.photometric_loss` of one (H, W, C) float32 CPU image through the Numba
    passes above (the gradient is computed with the loss)."""
    return _FusedPhotometricLoss.apply(img, ref, float(ssim_weight))
