"""The element-wise Numba passes of the HNN decoder's fused forward and backward
(`nehad.field.hnn_fused`, whose docstring names the quantities: z, a, d = act', e = act'',
u, delta and their gradients). Every per-row array is (2, N, H) (net, row, unit) and every
per-unit vector (2, H); each pass runs over both nets in row ranges in parallel. exp and log1p
are `nehad.field.vecmath`'s, which LLVM vectorises. The kernels are dtype-generic: float32 in
training, float64 in the tests."""

from __future__ import annotations

import numba

from nehad.field.vecmath import KERNEL_FASTMATH, exp_nonpositive, log1p_unit

TANH, SOFTPLUS, SILU = 0, 1, 2
ACTIVATION_CODES = {"tanh": TANH, "softplus": SOFTPLUS, "silu": SILU}


@numba.njit(inline="always")
def _activation(kind, z, one):
    """(act(z), act'(z), act''(z)) for activation code `kind` (docs/design.md section 4.3):
    tanh: a' = 1 - a^2, a'' = -2 a a';  softplus: a' = s = sigmoid(z), a'' = s (1 - s);
    SiLU a = z s: a' = s (1 + z (1 - s)), a'' = s (1 - s) (2 + z (1 - 2 s)). Every exponential
    is of -|z|, so nothing overflows."""
    two = one + one
    if kind == TANH:
        t = exp_nonpositive(-two * abs(z))
        a = (one - t) / (one + t)
        if z < 0:
            a = -a
        d = one - a * a
        return a, d, -two * a * d
    t = exp_nonpositive(-abs(z))
    s = (one if z >= 0 else t) / (one + t)
    if kind == SOFTPLUS:
        return max(z, one - one) + log1p_unit(t), s, s * (one - s)
    return z * s, s * (one + z * (one - s)), s * (one - s) * (two + z * (one - two * s))


#: Rows per range of the parallel loops. Fixed, not a share of the threads: the bias gradients
#: are summed per range and then over the ranges, so with the ranges set by the thread count
#: training would compute other last bits on another number of threads.
ROWS_PER_RANGE = 16


def _chunks(n: int) -> int:
    """The number of row ranges of the parallel loops over n rows (128 for a 2048-row block:
    many per thread, so the threads stay balanced)."""
    return max(1, -(-n // ROWS_PER_RANGE))


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _hidden_layer(kind, z, bias, a, d, e, one, chunks):
    """a, d, e = act, act', act'' of z + bias, for a hidden layer below the last."""
    nets, n = z.shape[0], z.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            b = bias[i]
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                zr, ar, dr, er = z[i, r], a[i, r], d[i, r], e[i, r]
                for j in range(zr.shape[0]):
                    av, dv, ev = _activation(kind, zr[j] + b[j], one)
                    ar[j] = av
                    dr[j] = dv
                    er[j] = ev


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _last_layer(kind, z, bias, w_out, d, e, delta, one, chunks):
    """d, e = act', act'' of z + bias and delta = d * w_out, for the last hidden layer (its
    activation value is not needed: only grad_h F is used)."""
    nets, n = z.shape[0], z.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            b, w = bias[i], w_out[i]
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                zr, dr, er, gr = z[i, r], d[i, r], e[i, r], delta[i, r]
                for j in range(zr.shape[0]):
                    _, dv, ev = _activation(kind, zr[j] + b[j], one)
                    dr[j] = dv
                    er[j] = ev
                    gr[j] = dv * w[j]


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _last_delta(kind, z, bias, w_out, delta, one, chunks):
    """delta = act'(z + bias) * w_out alone, for the last hidden layer in the forward (its d
    and e are computed again from z for the backward's rows: `_last_layer`); the same values
    as `_last_layer`'s delta."""
    nets, n = z.shape[0], z.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            b, w = bias[i], w_out[i]
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                zr, gr = z[i, r], delta[i, r]
                for j in range(zr.shape[0]):
                    _, dv, _ = _activation(kind, zr[j] + b[j], one)
                    gr[j] = dv * w[j]


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _product(x, y, out, chunks):
    """out = x * y (delta_k = d_k * u_k)."""
    nets, n = x.shape[0], x.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                xr, yr, orow = x[i, r], y[i, r], out[i, r]
                for j in range(xr.shape[0]):
                    orow[j] = xr[j] * yr[j]


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _delta_backward(ddelta, d, u, e, du, p, chunks):
    """du = ddelta * d and p = ddelta * u * e, for a hidden layer below the last."""
    nets, n = d.shape[0], d.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                gr, dr, ur, er, dur, pr = ddelta[i, r], d[i, r], u[i, r], e[i, r], du[i, r], p[i, r]
                for j in range(gr.shape[0]):
                    dur[j] = gr[j] * dr[j]
                    pr[j] = gr[j] * ur[j] * er[j]


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _last_backward(ddelta, d, e, w_out, dz, dw_parts, db_parts, chunks):
    """For the last hidden layer: dw_parts[c] = the row sums of ddelta * d over row range c
    (dL/dw_out), dz = ddelta * w_out * e and db_parts[c] its row sums (dL/db_L)."""
    nets, n = d.shape[0], d.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            w, sw, sb = w_out[i], dw_parts[c, i], db_parts[c, i]
            for j in range(sw.shape[0]):
                sw[j] = 0.0
                sb[j] = 0.0
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                gr, dr, er, zr = ddelta[i, r], d[i, r], e[i, r], dz[i, r]
                for j in range(gr.shape[0]):
                    sw[j] += gr[j] * dr[j]
                for j in range(gr.shape[0]):
                    zr[j] = gr[j] * w[j] * er[j]
                for j in range(gr.shape[0]):
                    sb[j] += zr[j]


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _hidden_backward(p, da, d, dz, db_parts, chunks):
    """dz = p + da * d and db_parts[c] its row sums over row range c (dL/db_k)."""
    nets, n = d.shape[0], d.shape[1]
    for c in numba.prange(chunks):
        for i in range(nets):
            sb = db_parts[c, i]
            for j in range(sb.shape[0]):
                sb[j] = 0.0
            for r in range(c * n // chunks, (c + 1) * n // chunks):
                pr, ar, dr, zr = p[i, r], da[i, r], d[i, r], dz[i, r]
                for j in range(pr.shape[0]):
                    zr[j] = pr[j] + ar[j] * dr[j]
                for j in range(pr.shape[0]):
                    sb[j] += zr[j]


@numba.njit(parallel=True, cache=True)
def live_rows(grads, live, chunks):
    """live[r] = whether row r of upstream gradients (k, b, W) (k arrays of b rows: the
    decoder's two nets, or the lookup's one (1, N, F)) has an entry that is not zero (a NaN
    counts as one). A row stops at its first such entry (numpy's `any` over a `g != 0`
    temporary took 0.5 ms for 16k rows of 64)."""
    n = grads.shape[1]
    for c in numba.prange(chunks):
        for r in range(c * n // chunks, (c + 1) * n // chunks):
            found = False
            for i in range(grads.shape[0]):
                row = grads[i, r]
                for j in range(row.shape[0]):
                    if row[j] != 0:
                        found = True
                        break
                if found:
                    break
            live[r] = found


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _field_rows(g, v, v_s, chunks):
    """v_s = g2 M^T = (g2_p, -g2_q) and v = g1 + v_s (paper Eq. (field)), g = (g1, g2) of a
    block (2, b, W)."""
    n, half = g.shape[1], g.shape[2] // 2
    for c in numba.prange(chunks):
        for r in range(c * n // chunks, (c + 1) * n // chunks):
            g1, g2, vr, sr = g[0, r], g[1, r], v[r], v_s[r]
            for j in range(half):
                sr[j] = g2[half + j]
                sr[half + j] = -g2[j]
            for j in range(2 * half):
                vr[j] = g1[j] + sr[j]


@numba.njit(parallel=True, fastmath=KERNEL_FASTMATH, cache=True)
def _field_grads(grad_v, grad_c, grad_s, grads, chunks):
    """grads = (dL/dg1, dL/dg2) of a block from the upstream gradients of v = v_c + v_s,
    v_c = g1 and v_s = g2 M^T: dL/dg1 = G_v + G_c, dL/dg2 = (G_v + G_s) M = (-G_p, G_q) for
    G = G_v + G_s = (G_q, G_p)."""
    n, half = grads.shape[1], grads.shape[2] // 2
    for c in numba.prange(chunks):
        for r in range(c * n // chunks, (c + 1) * n // chunks):
            gv, gc, gs, g1, g2 = grad_v[r], grad_c[r], grad_s[r], grads[0, r], grads[1, r]
            for j in range(2 * half):
                g1[j] = gv[j] + gc[j]
            for j in range(half):
                g2[j] = -(gv[half + j] + gs[half + j])
                g2[half + j] = gv[j] + gs[j]
