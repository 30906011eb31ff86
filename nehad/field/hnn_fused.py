"""The HNN decoder's input gradients (grad_h F1, grad_h F2) with a hand-written backward, as one
autograd Function whose element-wise work runs as Numba passes (issue 27; `field.hnn_grad =
"fused"`, docs/design.md section 4.4, docs/performance.md "The HNN decoder as one fused pass").

The forward is the closed form of docs/design.md section 4.4. For one scalar net F of depth L
(`nehad.field.hnn.ScalarNet`: L x [Linear, act], then Linear(hidden, 1, no bias) with weight
w_out), rows being Gaussians:

    z_k = a_{k-1} W_k^T + b_k,   a_0 = h,   a_k = act(z_k),  d_k = act'(z_k),  e_k = act''(z_k)
    u_L = w_out,   u_k = delta_{k+1} W_{k+1} (k < L),   delta_k = d_k * u_k
    g = grad_h F(h) = delta_1 W_1

Backward, for G = dL/dg (each product below differentiated by the product rule):

    dW_1 += delta_1^T G,   Ddelta_1 = G W_1^T
    k = 1 .. L:   Du_k = Ddelta_k * d_k,   P_k = Ddelta_k * u_k * e_k
                  k < L: dW_{k+1} += delta_{k+1}^T Du_k,   Ddelta_{k+1} = Du_k W_{k+1}^T
                  k = L: dw_out = sum over rows of Du_L
    Dz_L = P_L;   k = L .. 1:   dW_k += Dz_k^T a_{k-1},   db_k = sum over rows of Dz_k
                  k > 1: Dz_{k-1} = P_{k-1} + (Dz_k W_k) * d_{k-1}
    dh = Dz_1 W_1

F1 and F2 run side by side: every per-row array is (2, N, H) (net, Gaussian, unit) and every
per-unit vector (bias, w_out) is (2, H). The matrix products stay in torch (BLAS, batched over
the two nets); the element-wise work between two products is one Numba pass over both nets
(activation with its first and second derivative, the products, the row sums of the bias and
output-weight gradients), where the closed form through torch's autograd made some twenty
passes and as many autograd nodes. exp and log1p are `nehad.field.vecmath`'s, which LLVM
vectorises. The kernels are dtype-generic: float32 in training, float64 in the tests (where
they agree with autograd to rounding, tests/test_hnn_fused.py).

With the kinetic term (`FieldConfig.hnn_quadratic`: F_k += h^T S_k h / 2, S_k = (A_k + A_k^T) / 2)
each g_k gains S_k h in the same blocks; its backward adds G_k S_k to dh and h^T G_k to dS_k,
dL/dA_k = (dS_k + dS_k^T) / 2.

With `fused_field`'s `trunk` the trunk's Linear(F, W) in front of the decoder runs in the same
blocks: h = f W_t^T + b_t before the nets, and after them df = dh W_t, dW_t += dh^T f, db_t +=
the row sums of dh, on the rows with a gradient only (below). With its `heads` the stacked
adapters and the Verlet force behind the decoder run there too: out = v A^T + a and force = v_c
A_mu'^T per block, and dL/dv = G_out A, dL/dv_c = G_force A_mu' start the block's backward.
The heads are linear in v and v_c, so they read g1, g2 (and, with the kinetic term, h)
straight: v, v_s and S_k h are then not formed per Gaussian (`_Heads`).

The backward leaves out the rows whose upstream gradient is zero (a Gaussian that no pixel of the
view sees): every term above is linear in G, so such a row adds zeros to every gradient. The
sums over the remaining rows regroup, so the parameters' gradients may differ from the full
backward's in their last bits; and a row with a non-finite saved value but no gradient no longer
turns the parameters' gradients into NaN (0 x inf), which the kernels' fast-math flags did not
promise either.

The backward is not itself differentiable (no double backward through it): nothing in training
needs one; `hnn_grad="closed_form"` is the differentiable-twice reference.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numba
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from nehad.field.vecmath import KERNEL_FASTMATH, exp_nonpositive, log1p_unit

TANH, SOFTPLUS, SILU = 0, 1, 2
ACTIVATION_CODES = {"tanh": TANH, "softplus": SOFTPLUS, "silu": SILU}
#: Rows per block of the forward and the backward: a block's (2, rows, 64) float32 temporaries
#: are 1 MB each and stay in the cache between a product and the pass that reads them. The
#: decoder's forward + backward at 10k rows, 1 thread, paired: 101 ms unblocked, 60-67 ms with
#: blocks of 1536 .. 4096 rows, 73 ms with 1024, 82 ms with 512 (docs/performance.md).
BLOCK_ROWS = 2048


# ----------------------------------------------------------------------------- element-wise
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
def _live_rows(grads, live, chunks):
    """live[r] = whether row r of a block's (2, b, W) upstream gradients has an entry that is
    not zero (a NaN counts as one)."""
    n = grads.shape[1]
    for c in numba.prange(chunks):
        for r in range(c * n // chunks, (c + 1) * n // chunks):
            found = False
            for i in range(grads.shape[0]):
                row = grads[i, r]
                for j in range(row.shape[0]):
                    if row[j] != 0:
                        found = True
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


# ----------------------------------------------------------------------------- the Function
def _np(t: torch.Tensor) -> np.ndarray:
    """The numpy view of a contiguous CPU tensor (no copy)."""
    return t.detach().numpy()


def _per_net(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(2, ., .) = x[i] @ y[i] for both nets, one batched product."""
    return torch.bmm(x, y)


class _Nets(NamedTuple):
    """Both nets' parameters stacked net-major, as the kernels read them."""

    weights: list  # W_k, (2, H, in) tensors
    biases: list  # b_k, (2, H) arrays
    w_out: np.ndarray  # (2, H)
    kind: int  # activation code
    one: object  # 1 in the dtype of the kernels (numpy scalar)

    @property
    def depth(self) -> int:
        return len(self.weights)

    @staticmethod
    def stack(params, kind: int) -> "_Nets":
        """From F1's W_1, b_1, ..., W_L, b_L, w_out followed by F2's."""
        per_net = len(params) // 2
        nets = (params[:per_net], params[per_net:])
        depth = (per_net - 1) // 2
        weights = [torch.stack([net[2 * k].detach() for net in nets]) for k in range(depth)]
        biases = [np.stack([_np(net[2 * k + 1]) for net in nets]) for k in range(depth)]
        w_out = np.stack([_np(net[-1]).reshape(-1) for net in nets])
        return _Nets(weights, biases, w_out, kind, w_out.dtype.type(1.0))


class _Saved(NamedTuple):
    """What the backward of one block of rows reads (module docstring's names, per layer)."""

    acts: list  # a_0 = h, a_1, ..., a_{L-1}
    derivs: list  # d_k
    curvs: list  # e_k
    us: list  # u_k, k < L (None for k = L)
    deltas: list  # delta_k


def _forward_block(nets: _Nets, h: torch.Tensor, g: Optional[torch.Tensor]) -> _Saved:
    """g[i] = grad_h F_i(h) for a block of rows h (b, W), g (2, b, W) views of the output; g
    None: not formed (`_Composed` reads delta_1 instead)."""
    b = h.shape[0]
    chunks = _chunks(b)
    acts, derivs, curvs = [h], [], []
    delta_last = None
    for k in range(nets.depth):
        x = h.expand(2, b, h.shape[1]) if k == 0 else acts[k]
        z = torch.bmm(x, nets.weights[k].transpose(1, 2))
        d, e = torch.empty_like(z), torch.empty_like(z)
        if k < nets.depth - 1:
            a = torch.empty_like(z)
            _hidden_layer(nets.kind, _np(z), nets.biases[k], _np(a), _np(d), _np(e), nets.one,
                          chunks)
            acts.append(a)
        else:
            delta_last = torch.empty_like(z)
            _last_layer(nets.kind, _np(z), nets.biases[k], nets.w_out, _np(d), _np(e),
                        _np(delta_last), nets.one, chunks)
        derivs.append(d)
        curvs.append(e)
    deltas = [None] * nets.depth
    deltas[-1] = delta_last
    us = [None] * nets.depth
    for k in range(nets.depth - 2, -1, -1):
        us[k] = _per_net(deltas[k + 1], nets.weights[k + 1])
        deltas[k] = torch.empty_like(us[k])
        _product(_np(derivs[k]), _np(us[k]), _np(deltas[k]), chunks)
    if g is not None:
        torch.bmm(deltas[0], nets.weights[0], out=g)
    return _Saved(acts, derivs, curvs, us, deltas)


def _backward_block(nets: _Nets, saved: _Saved, grads, grad_h: torch.Tensor, d_weights: list,
                    d_biases: np.ndarray, d_w_out: np.ndarray,
                    d_delta: Optional[torch.Tensor] = None) -> None:
    """For one block of rows: grad_h (b, W) = dL/dh of the block, and the block's share of the
    parameters' gradients added to d_weights (W_k's, (2, H, in)), d_biases (L, 2, H) and
    d_w_out (2, H); grads (2, b, W) = (dL/dg1, dL/dg2) of the block. Or, given `d_delta` =
    dL/ddelta_1 (2, b, H) instead of grads (`_Composed`, where g is not formed), from there on:
    d_weights[0] then gets only the first layer's input side, dz^T h."""
    acts, derivs, curvs, us, deltas = saved
    h, depth = acts[0], nets.depth
    b, hidden = h.shape[0], nets.weights[0].shape[1]
    chunks = _chunks(b)
    parts = np.empty((chunks, 2, hidden), dtype=nets.w_out.dtype)
    if d_delta is None:
        d_delta = torch.bmm(grads, nets.weights[0].transpose(1, 2))
        d_weights[0].baddbmm_(deltas[0].transpose(1, 2), grads)
    partial = [None] * depth  # P_k
    for k in range(depth - 1):
        du, p = torch.empty_like(d_delta), torch.empty_like(d_delta)
        _delta_backward(_np(d_delta), _np(derivs[k]), _np(us[k]), _np(curvs[k]), _np(du),
                        _np(p), chunks)
        partial[k] = p
        d_weights[k + 1].baddbmm_(deltas[k + 1].transpose(1, 2), du)
        d_delta = _per_net(du, nets.weights[k + 1].transpose(1, 2))
    dz = torch.empty_like(d_delta)
    dw_parts = np.empty_like(parts)
    _last_backward(_np(d_delta), _np(derivs[-1]), _np(curvs[-1]), nets.w_out, _np(dz),
                   dw_parts, parts, chunks)
    d_w_out += dw_parts.sum(axis=0)
    for k in range(depth - 1, -1, -1):
        d_biases[k] += parts.sum(axis=0)
        below = h.expand(2, b, h.shape[1]) if k == 0 else acts[k]
        d_weights[k].baddbmm_(dz.transpose(1, 2), below)
        if k == 0:
            break
        da = _per_net(dz, nets.weights[k])
        dz_below = torch.empty_like(dz)
        _hidden_backward(_np(partial[k - 1]), _np(da), _np(derivs[k - 1]), _np(dz_below),
                         parts, chunks)
        dz = dz_below
    torch.mm(dz[0], nets.weights[0][0], out=grad_h)
    grad_h.addmm_(dz[1], nets.weights[0][1])


#: The backward runs on the rows whose upstream gradient is not zero when they are fewer than
#: this share of a block (a Gaussian that no pixel of the view sees gets none: about half of a
#: MuJoCo scene's in a view, docs/performance.md); their saved values are gathered first.
COMPACT_BELOW = 0.85


def _rows_with_gradient(grads: torch.Tensor):
    """The rows (int64 indices) of a block's (2, b, W) upstream gradients with a non-zero
    entry, or None when they are too many to be worth gathering (`COMPACT_BELOW`)."""
    live = np.empty(grads.shape[1], dtype=np.bool_)
    _live_rows(_np(grads), live, _chunks(grads.shape[1]))
    if np.count_nonzero(live) >= COMPACT_BELOW * grads.shape[1]:
        return None
    return np.flatnonzero(live)


def _compact(saved: _Saved, rows: np.ndarray) -> _Saved:
    """A block's saved values at `rows` only (row axis 0 of h, 1 of the per-net arrays). The
    element-wise passes reading the full arrays through `rows` instead measured slower than
    these copies (docs/performance.md)."""
    index = torch.from_numpy(rows)

    def pick(arrays, axis):
        return [None if a is None else a.index_select(axis, index) for a in arrays]

    return _Saved(pick(saved.acts[:1], 0) + pick(saved.acts[1:], 1), pick(saved.derivs, 1),
                  pick(saved.curvs, 1), pick(saved.us, 1), pick(saved.deltas, 1))


def _backward_rows(nets: _Nets, block: _Saved, grads: torch.Tensor, quads, out_all: torch.Tensor,
                   d_weights: list, d_biases: np.ndarray, d_w_out: np.ndarray, d_quads):
    """`_backward_block` of one block on its rows with a gradient only (`_rows_with_gradient`),
    plus the kinetic term's share: dh += G_k S_k, dS_k += h^T G_k. Returns (rows, dh): rows
    None and dh = `out_all` (b, W) when every row went through; else the rows (int64) and
    their dh (len(rows), W), or None when there is none (dh of the other rows is 0)."""
    rows = _rows_with_gradient(grads)
    if rows is not None:  # only those rows: the others add zeros everywhere
        if len(rows) == 0:
            return rows, None
        block, grads = _compact(block, rows), grads.index_select(1, torch.from_numpy(rows))
    out = out_all if rows is None else torch.empty((len(rows), out_all.shape[1]),
                                                   dtype=out_all.dtype)
    _backward_block(nets, block, grads, out, d_weights, d_biases, d_w_out)
    if quads is not None:
        hb = block.acts[0]
        for i in range(2):
            out.addmm_(grads[i], quads[i])
        d_quads.baddbmm_(hb.T.expand(2, hb.shape[1], hb.shape[0]), grads)
    return rows, out


def _place(dest: torch.Tensor, rows, part) -> None:
    """dest = part at `rows` and 0 elsewhere (`_backward_rows`' result; rows None: every row,
    already in place when part is dest)."""
    if rows is None:
        if part is not dest:
            dest.copy_(part)
        return
    dest.zero_()
    if part is not None:
        dest.index_copy_(0, torch.from_numpy(rows), part)


class _Trunk(NamedTuple):
    """The trunk's Linear(F, W) fused in front of the decoder (`fused_field`'s `trunk`): h = f
    W^T + b per block, and its backward on the rows with a gradient only."""

    weight: torch.Tensor  # (W, F)
    bias: torch.Tensor  # (W,)

    def forward(self, f: torch.Tensor, h: torch.Tensor) -> None:
        """h = f W^T + b, for a block (rows of f and h)."""
        torch.addmm(self.bias, f, self.weight.T, out=h)

    def backward(self, f: torch.Tensor, rows, dh, grad_f: torch.Tensor, d_weight: torch.Tensor,
                 d_bias: torch.Tensor) -> None:
        """A block's dL/df (into grad_f, 0 off `rows`) and its share of dL/dW, dL/db, from
        `_backward_rows`' (rows, dh)."""
        if dh is None:
            grad_f.zero_()
            return
        if rows is None:
            torch.mm(dh, self.weight, out=grad_f)
            below = f
        else:
            _place(grad_f, rows, torch.mm(dh, self.weight))
            below = f.index_select(0, torch.from_numpy(rows))
        d_weight.addmm_(dh.T, below)
        d_bias += dh.sum(dim=0)


def _blocks(n: int):
    """The row blocks (lo, hi) of `BLOCK_ROWS` rows."""
    return [(lo, min(n, lo + BLOCK_ROWS)) for lo in range(0, n, BLOCK_ROWS)]


def symplectic(g: torch.Tensor) -> torch.Tensor:
    """g M^T = (g_p, -g_q) for g = (g_q, g_p) on the last axis, M = [[0, I], [-I, 0]] (paper
    Eq. (field): v_s = g2 M^T)."""
    d = g.shape[-1] // 2
    return torch.cat([g[..., d:], -g[..., :d]], dim=-1)


def symplectic_transpose(y: torch.Tensor) -> torch.Tensor:
    """y M = (-y_p, y_q) on the last axis: the transpose of `symplectic` (the gradient of
    v_s = g M^T is G M)."""
    d = y.shape[-1] // 2
    return torch.cat([-y[..., d:], y[..., :d]], dim=-1)


class _Heads(NamedTuple):
    """The adapters and the Verlet force fused behind the decoder (`fused_field`'s `heads`):
    out = v A^T + a (the stacked adapters, (K, W) and (K,)) and force = v_c A_mu'^T ((3, W), no
    bias). Both are linear in v and v_c, so they are read straight from the nets' g1, g2 and,
    with the kinetic terms, from h (docs/design.md section 4.4):

        v = g1 + h S_1 + (g2 + h S_2) M^T,  v_c = g1 + h S_1
        [out - a | force] = g1 P0 + [g2 P1 | 0] + h K

    with P0 = [A^T | A_mu'^T] (W, K + 3), P1 = M^T A^T (W, K), K = [C A^T | S_1 A_mu'^T] and
    C = S_1 + S_2 M^T. Neither v, v_c nor S_k h is formed per Gaussian: three products of
    13 (or 10) columns a row, where v, v_s and the two (W x W) products S_k h took two
    element-wise passes and 2 W^2 multiply-adds. Backward: dL/dg1 = G P0^T, dL/dg2 = G_out P1^T,
    dh += G K^T (G = [G_out | G_force]), and the weights' gradients from dP0 = g1^T G,
    dP1 = g2^T G_out and dK = h^T G, summed over the blocks, once per call (`weight_grads`)."""

    weight: torch.Tensor  # A (K, W)
    bias: torch.Tensor  # a (K,)
    force_weight: torch.Tensor  # A_mu' (3, W)
    p0: torch.Tensor  # (W, K + 3)
    p1: torch.Tensor  # (W, K)
    s1: Optional[torch.Tensor]  # (W, W) S_1, or None without the kinetic terms
    c: Optional[torch.Tensor]  # (W, W) C
    k: Optional[torch.Tensor]  # (W, K + 3) K

    @staticmethod
    def of(weight, bias, force_weight, quads) -> "_Heads":
        """From A, a, A_mu' and the kinetic terms' (2, W, W) S_k (or None)."""
        p0 = torch.cat([weight.T, force_weight.T], dim=1).contiguous()
        p1 = symplectic_transpose(weight).T.contiguous()
        s1 = c = k = None
        if quads is not None:
            s1 = quads[0]
            c = s1 + symplectic(quads[1])
            k = torch.cat([c @ weight.T, s1 @ force_weight.T], dim=1).contiguous()
        return _Heads(weight, bias, force_weight, p0, p1, s1, c, k)

    @property
    def n_out(self) -> int:
        return self.weight.shape[0]

    def forward(self, g: torch.Tensor, h: torch.Tensor, both: torch.Tensor) -> None:
        """both (b, K + 3) = [out - a | force] of a block from its g = (g1, g2) and h."""
        torch.mm(g[0], self.p0, out=both)
        both[:, :self.n_out].addmm_(g[1], self.p1)
        if self.k is not None:
            both.addmm_(h, self.k)

    def backward(self, g: torch.Tensor, h: torch.Tensor, g_out, g_force, grads: torch.Tensor,
                 sums: list) -> torch.Tensor:
        """grads (2, b, W) = (dL/dg1, dL/dg2) of a block from the upstream gradients of out and
        force (None: zero), and its share of dP0, dP1, dK, da added to `sums`. Returns G."""
        b, dtype = h.shape[0], h.dtype
        g_out = torch.zeros((b, self.n_out), dtype=dtype) if g_out is None else g_out
        g_force = torch.zeros((b, 3), dtype=dtype) if g_force is None else g_force
        both = torch.cat([g_out, g_force], dim=1)
        torch.mm(both, self.p0.T, out=grads[0])
        torch.mm(g_out, self.p1.T, out=grads[1])
        d_p0, d_p1, d_k, d_bias = sums
        d_p0.addmm_(g[0].T, both)
        d_p1.addmm_(g[1].T, g_out)
        if d_k is not None:
            d_k.addmm_(h.T, both)
        d_bias += g_out.sum(dim=0)
        return both

    def add_dh(self, both: torch.Tensor, rows, dh) -> None:
        """dh += G K^T (dh as `_backward_rows` gives it: every row, the rows `rows`, or None
        where no row has a gradient: G K^T is then 0 as well)."""
        if self.k is None or dh is None:
            return
        if rows is not None:
            both = both.index_select(0, torch.from_numpy(rows))
        dh.addmm_(both, self.k.T)

    def zero_sums(self) -> list:
        """The accumulators of `backward`: dP0, dP1, dK (None without it), da."""
        return [torch.zeros_like(self.p0), torch.zeros_like(self.p1),
                None if self.k is None else torch.zeros_like(self.k),
                torch.zeros_like(self.bias)]

    def weight_grads(self, sums: list):
        """(dA, da, dA_mu', dS) from the summed dP0, dP1, dK: dA = dP0_out^T + dP1^T M^T
        + dK_out^T C, dA_mu' = dP0_f^T + dK_f^T S_1, and dS_k (S_k taken as free matrices:
        dS_1 = dK_out A + dK_f A_mu', dS_2 = dK_out A M), or None without the kinetic terms."""
        d_p0, d_p1, d_k, d_bias = sums
        n = self.n_out
        d_a = d_p0[:, :n].T + symplectic(d_p1.T)
        d_f = d_p0[:, n:].T.contiguous()
        d_s = None
        if d_k is not None:
            dk_out, dk_f = d_k[:, :n], d_k[:, n:]
            d_a = d_a + dk_out.T @ self.c
            d_f = d_f + dk_f.T @ self.s1
            d_s = torch.stack([dk_out @ self.weight + dk_f @ self.force_weight,
                               symplectic_transpose(dk_out @ self.weight)])
        return d_a, d_bias, d_f, d_s


class _Composed(NamedTuple):
    """The training path (`fused_field` with both `trunk` and `heads`): the trunk, the nets'
    first layers and the heads composed into smaller maps. Every map from the trunk's input f to
    the heads' output is linear except the nets' activations, so

        z_1,k = h W1_k^T + b1_k = f C_k^T + c_k,    C_k = W1_k Wt,  c_k = W1_k bt + b1_k
        [out | force] = g1 P0 + [g2 P1 | 0] + h K + [a | 0]
                      = delta_1,1 Q_1 + delta_1,2 Q_2 + f KW + const,
        Q_1 = W1_1 P0,  Q_2 = [W1_2 P1 | 0],  KW = Wt^T K,  const = [a | 0] + bt K

    (g_k = delta_1,k W1_k, `_Heads` for P0, P1, K). Neither h nor g is formed: a row costs the
    two (H x F) products of z and small ones of J = K + 3 columns, where the trunk, z and g took
    five (W x W)-sized products forward and the backward eight more (the trunk's two, g's two
    pairs, dL/dh). The backward (`backward_block`) starts at dL/ddelta_1 = G Q_k^T, and the
    parameters' gradients come from those of C, c, Q, KW and const once per call
    (`parameter_grads`): dW1_k = dC_k Wt^T + dc_k bt^T + dQ_k P_k^T, dWt = sum_k W1_k^T dC_k
    + K dKW^T, dbt = sum_k W1_k^T dc_k + K dconst, dP0 = W1_1^T dQ_1, dP1 = W1_2^T dQ_2,
    dK = Wt dKW + bt dconst^T, da = dconst (its first K entries)."""

    nets: _Nets  # the nets with C in place of W1 and c in place of b1
    w1: torch.Tensor  # (2, H, W) the nets' own W1
    trunk: _Trunk
    tail: _Heads
    q: torch.Tensor  # (2, H, J): Q_1, Q_2
    kw: Optional[torch.Tensor]  # (F, J) or None without the kinetic terms
    const: torch.Tensor  # (J,)

    @staticmethod
    def of(nets: _Nets, trunk: _Trunk, tail: _Heads) -> "_Composed":
        w1, wt, bt = nets.weights[0], trunk.weight, trunk.bias
        c = torch.matmul(w1, wt)  # (2, H, F)
        c_bias = (torch.matmul(w1, bt) + torch.from_numpy(nets.biases[0])).numpy()
        n = tail.n_out
        q = torch.zeros((2, w1.shape[1], n + 3), dtype=w1.dtype)
        q[0] = w1[0] @ tail.p0
        q[1, :, :n] = w1[1] @ tail.p1
        const = torch.cat([tail.bias, torch.zeros(3, dtype=w1.dtype)])
        kw = None
        if tail.k is not None:
            kw = (wt.T @ tail.k).contiguous()
            const = const + bt @ tail.k
        composed = nets._replace(weights=[c.contiguous(), *nets.weights[1:]],
                                 biases=[c_bias, *nets.biases[1:]])
        return _Composed(composed, w1, trunk, tail, q, kw, const)

    def forward_block(self, f: torch.Tensor, both: torch.Tensor) -> _Saved:
        """both (b, J) = [out | force] of a block of rows f (b, F); what its backward reads."""
        saved = _forward_block(self.nets, f, None)
        d1 = saved.deltas[0]
        torch.addmm(self.const, d1[0], self.q[0], out=both)
        both.addmm_(d1[1], self.q[1])
        if self.kw is not None:
            both.addmm_(f, self.kw)
        return saved

    def zero_sums(self) -> list:
        """The per-call accumulators: dC (2, H, F), dc (L, 2, H), dw_out, the deeper layers'
        dW, dQ, dKW (or None), dconst."""
        nets = self.nets
        return [[torch.zeros_like(w) for w in nets.weights],
                np.zeros((nets.depth, *nets.w_out.shape), dtype=nets.w_out.dtype),
                np.zeros_like(nets.w_out), torch.zeros_like(self.q),
                None if self.kw is None else torch.zeros_like(self.kw),
                torch.zeros_like(self.const)]

    def backward_block(self, saved: _Saved, grad: torch.Tensor, grad_f: torch.Tensor,
                       sums: list) -> None:
        """grad_f (b, F) = dL/df of a block (0 on its rows without a gradient) from grad (b, J)
        = dL/d[out | force] (contiguous), and the block's share of the sums (`zero_sums`)."""
        f = saved.acts[0]
        d_weights, d_biases, d_w_out, d_q, d_kw, d_const = sums
        rows = _rows_with_gradient(grad[None])
        if rows is not None:
            if len(rows) == 0:
                grad_f.zero_()
                return
            saved, grad = _compact(saved, rows), grad.index_select(0, torch.from_numpy(rows))
            f = saved.acts[0]
        m = grad.shape[0]
        both = grad.expand(2, m, grad.shape[1])
        d_delta = torch.bmm(both, self.q.transpose(1, 2))
        d_q.baddbmm_(saved.deltas[0].transpose(1, 2), both)
        out = grad_f if rows is None else torch.empty((m, grad_f.shape[1]), dtype=grad_f.dtype)
        _backward_block(self.nets, saved, None, out, d_weights, d_biases, d_w_out, d_delta)
        if self.kw is not None:
            out.addmm_(grad, self.kw.T)
            d_kw.addmm_(f.T, grad)
        d_const += grad.sum(dim=0)
        if rows is not None:
            _place(grad_f, rows, out)

    def parameter_grads(self, sums: list):
        """(the nets' dW_k (2, H, in) per layer, db_k (L, 2, H), dw_out (2, H), (dWt, dbt), the
        tail's sums for `_Heads.weight_grads`) from the per-call sums (class docstring); db_1 is
        dc itself."""
        d_weights, d_biases, d_w_out, d_q, d_kw, d_const = sums
        wt, bt, tail, w1 = self.trunk.weight, self.trunk.bias, self.tail, self.w1
        n = tail.n_out
        d_c, d_cb = d_weights[0], torch.from_numpy(d_biases[0].copy())
        d_w1 = torch.matmul(d_c, wt.T) + d_cb[:, :, None] * bt[None, None, :]
        d_w1[0] += d_q[0] @ tail.p0.T
        d_w1[1] += d_q[1, :, :n] @ tail.p1.T
        d_wt = torch.einsum("khw,khf->wf", w1, d_c)
        d_bt = torch.einsum("khw,kh->w", w1, d_cb)
        d_p0 = w1[0].T @ d_q[0]
        d_p1 = w1[1].T @ d_q[1, :, :n]
        d_k = None
        if self.kw is not None:
            d_k = wt @ d_kw + bt[:, None] * d_const[None, :]
            d_wt = d_wt + tail.k @ d_kw.T
            d_bt = d_bt + tail.k @ d_const
        return ([d_w1, *d_weights[1:]], d_biases, d_w_out, (d_wt, d_bt),
                [d_p0, d_p1, d_k, d_const[:n].clone()])


def _composed_backward(composed: _Composed, saved: list, xd: torch.Tensor, upstream,
                       quadratic: bool) -> tuple:
    """`FusedInputGradients.backward` of the training path (`_Composed`)."""
    tail, n, dtype = composed.tail, xd.shape[0], xd.dtype
    grad = torch.zeros((n, tail.n_out + 3), dtype=dtype)
    for part, u in ((grad[:, :tail.n_out], upstream[0]), (grad[:, tail.n_out:], upstream[1])):
        if u is not None:
            part.copy_(u)
    grad_x = torch.empty(xd.shape, dtype=dtype)
    sums = composed.zero_sums()
    for (lo, hi), block in zip(_blocks(n), saved):
        composed.backward_block(block, grad[lo:hi], grad_x[lo:hi], sums)
    d_weights, d_biases, d_w_out, d_head, tail_sums = composed.parameter_grads(sums)
    net_grads = []
    for i in range(2):
        for k in range(composed.nets.depth):
            net_grads += [d_weights[k][i], torch.from_numpy(d_biases[k, i].copy())]
        net_grads.append(torch.from_numpy(d_w_out[i].copy()).reshape(1, -1))
    d_a, d_bias, d_force, d_quads = tail.weight_grads(tail_sums)
    if quadratic:  # S = (A + A^T) / 2: dL/dA = (dS + dS^T) / 2
        net_grads += list(0.5 * (d_quads + d_quads.transpose(1, 2)))
    net_grads += [*d_head, d_a, d_bias, d_force]
    return (grad_x, None, None, None, None, None, None, *net_grads)


class FusedInputGradients(torch.autograd.Function):
    """(grad_h F1, grad_h F2), each (N, W), of the two scalar nets given by their parameters
    (module docstring); with `field` the decoder's outputs (v, v_c, v_s) instead (v_c = g1,
    v_s = g2 M^T, v = v_c + v_s; paper Eq. (field)), so that no torch op (and no autograd node)
    follows. Inputs: x, the activation code, whether to keep what the backward needs, `field`,
    `quadratic`, `trunk`, then each net's W_1, b_1, ..., W_L, b_L, w_out (F1's, then F2's),
    then with `quadratic` the kinetic terms' A_1, A_2 (W, W): each g_k then gains S_k h,
    S_k = (A_k + A_k^T) / 2 (`fused_field`), in the same blocks, so that the kinetic term adds
    no autograd node either; then with `trunk` the trunk's Linear(F, W) weight and bias: x is
    then the trunk's input f (N, F) and h = f W^T + b is computed block by block (`_Trunk`);
    else x is h (N, W); then with `heads` the stacked adapters' weight and bias and the force's
    weight (`_Heads`): the result is then (v A^T + a, v_c A_mu'^T) alone, read from g1, g2
    (and h for the kinetic terms) without forming v.

    Forward and backward run block by block (`BLOCK_ROWS` rows), so that the temporaries of a
    block stay in the cache between the products and the element-wise passes."""

    @staticmethod
    def forward(ctx, x, kind, keep, field, quadratic, trunk, heads, *params):
        ctx.set_materialize_grads(False)
        before_tail = params[:-3] if heads else params
        head = _Trunk(*[p.detach() for p in before_tail[-2:]]) if trunk else None
        params_nets = before_tail[:-2] if trunk else before_tail
        quads = _kinetic(params_nets[-2:]) if quadratic else None
        tail = _Heads.of(*[p.detach() for p in params[-3:]], quads) if heads else None
        nets = _Nets.stack(params_nets[:-2] if quadratic else params_nets, kind)
        xd = x.detach().contiguous()
        n = xd.shape[0]
        width = nets.weights[0].shape[2]
        composed = _Composed.of(nets, head, tail) if head is not None and tail is not None else None
        hd = xd if head is None or composed is not None else torch.empty((n, width), dtype=xd.dtype)
        g = None if composed is not None else torch.empty((2, n, width), dtype=xd.dtype)
        if field and tail is None:
            v, v_s = torch.empty((n, width), dtype=xd.dtype), torch.empty((n, width), dtype=xd.dtype)
        if tail is not None:  # [out - a | force]
            both = torch.empty((n, tail.n_out + 3), dtype=xd.dtype)
        saved = []
        for lo, hi in _blocks(n):
            if composed is not None:  # the training path: neither h nor g is formed
                saved.append(composed.forward_block(xd[lo:hi], both[lo:hi]))
                continue
            if head is not None:
                head.forward(xd[lo:hi], hd[lo:hi])
            saved.append(_forward_block(nets, hd[lo:hi], g[:, lo:hi]))
            if tail is not None:
                tail.forward(g[:, lo:hi], hd[lo:hi], both[lo:hi])
                continue
            if quads is not None:  # g_k += S_k h (S_k symmetric: h S_k)
                g[:, lo:hi].baddbmm_(hd[lo:hi].expand(2, hi - lo, width), quads)
            if field:
                _field_rows(_np(g[:, lo:hi]), _np(v[lo:hi]), _np(v_s[lo:hi]), _chunks(hi - lo))
        if keep:
            ctx.save_for_backward(x, *params)
            ctx.kept = (nets, saved, field, quads, head, xd, tail, g if tail is not None else None,
                        composed)
        if composed is not None:  # const holds the adapters' bias
            return both[:, :tail.n_out], both[:, tail.n_out:]
        if tail is not None:
            return both[:, :tail.n_out] + tail.bias, both[:, tail.n_out:]
        return (v, g[0], v_s) if field else (g[0], g[1])

    @staticmethod
    @once_differentiable
    def backward(ctx, *upstream):
        ctx.saved_tensors  # raises if x or a parameter was modified in place since the forward
        nets, saved, field, quads, head, xd, tail, g_all, composed = ctx.kept
        n, width, dtype = xd.shape[0], nets.weights[0].shape[2], xd.dtype
        if composed is not None:
            return _composed_backward(composed, saved, xd, upstream, quads is not None)
        if tail is not None:  # the adapters' and the force's upstream gradients (None: zero)
            g_out, g_force = [None if u is None else u.contiguous() for u in upstream]
            sums = tail.zero_sums()
        else:  # an output nobody used has no gradient: zeros, as autograd would give
            upstream = [torch.zeros((n, width), dtype=dtype) if u is None else u.contiguous()
                        for u in upstream]
        grad_x = torch.empty(xd.shape, dtype=dtype)
        dh_all = torch.empty((min(n, BLOCK_ROWS), width), dtype=dtype) if head else None
        d_quads = None if quads is None or tail is not None else torch.zeros_like(quads)
        d_weights = [torch.zeros_like(w) for w in nets.weights]
        d_biases = np.zeros((nets.depth, *nets.w_out.shape), dtype=nets.w_out.dtype)
        d_w_out = np.zeros_like(nets.w_out)
        if head is not None:
            d_head = (torch.zeros_like(head.weight), torch.zeros_like(head.bias))
        for (lo, hi), block in zip(_blocks(n), saved):
            if tail is not None:  # (dL/dg1, dL/dg2) of the block straight from the heads
                grads = torch.empty((2, hi - lo, width), dtype=dtype)
                both = tail.backward(g_all[:, lo:hi], block.acts[0],
                                     None if g_out is None else g_out[lo:hi],
                                     None if g_force is None else g_force[lo:hi], grads, sums)
            elif field:
                grads = torch.empty((2, hi - lo, width), dtype=dtype)
                _field_grads(*[_np(u[lo:hi]) for u in upstream], _np(grads), _chunks(hi - lo))
            else:
                grads = torch.stack([u[lo:hi] for u in upstream])
            out_all = grad_x[lo:hi] if head is None else dh_all[:hi - lo]
            rows, dh = _backward_rows(nets, block, grads, quads if tail is None else None,
                                      out_all, d_weights, d_biases, d_w_out, d_quads)
            if tail is not None:
                tail.add_dh(both, rows, dh)
            if head is None:
                _place(grad_x[lo:hi], rows, dh)
            else:
                head.backward(xd[lo:hi], rows, dh, grad_x[lo:hi], *d_head)
        net_grads = []
        for i in range(2):
            for k in range(nets.depth):
                net_grads += [d_weights[k][i], torch.from_numpy(d_biases[k, i].copy())]
            net_grads.append(torch.from_numpy(d_w_out[i].copy()).reshape(1, -1))
        if tail is not None:
            d_a, d_bias, d_force, d_quads = tail.weight_grads(sums)
        if quads is not None:  # S = (A + A^T) / 2: dL/dA = (dS + dS^T) / 2
            net_grads += list(0.5 * (d_quads + d_quads.transpose(1, 2)))
        if head is not None:
            net_grads += list(d_head)
        if tail is not None:
            net_grads += [d_a, d_bias, d_force]
        return (grad_x, None, None, None, None, None, None, *net_grads)


# ----------------------------------------------------------------------------- entry points
def net_parameters(net) -> list[torch.Tensor]:
    """A `ScalarNet`'s W_1, b_1, ..., W_L, b_L, w_out, in `FusedInputGradients`' order."""
    params = []
    for lin in net.hidden_layers:
        params += [lin.weight, lin.bias]
    return params + [net.out.weight]


def fused_supported(f1, f2, h: torch.Tensor, quads=None, trunk=None, heads=None) -> bool:
    """Whether `fused_input_gradients` (or `fused_field`) can run: CPU float32 or float64 input,
    the same dtype for every parameter (the kinetic terms' `quads`, the `trunk`'s and the
    `heads`' too), the same depth and activation in both nets."""
    params = net_parameters(f1) + net_parameters(f2) + list(trunk or ()) + list(heads or ())
    return (h.device.type == "cpu" and h.dtype in (torch.float32, torch.float64)
            and f1.activation == f2.activation and f1.activation in ACTIVATION_CODES
            and len(f1.hidden_layers) == len(f2.hidden_layers)
            and all(p.dtype == h.dtype and p.device.type == "cpu"
                    for p in params + list(quads or ())))


def _kinetic(quads) -> torch.Tensor:
    """(2, W, W) the symmetric S_k = (A_k + A_k^T) / 2 of the kinetic terms' A_1, A_2."""
    a = torch.stack([q.detach() for q in quads])
    return 0.5 * (a + a.transpose(1, 2))


def _apply(f1, f2, x: torch.Tensor, field: bool, quads=None, trunk=None, heads=None):
    params = (net_parameters(f1) + net_parameters(f2) + list(quads or ()) + list(trunk or ())
              + list(heads or ()))
    keep = torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in params))
    return FusedInputGradients.apply(x, ACTIVATION_CODES[f1.activation], keep, field,
                                     quads is not None, trunk is not None, heads is not None,
                                     *params)


def fused_input_gradients(f1, f2, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(grad_h f1(h), grad_h f2(h)) of two `ScalarNet`s by `FusedInputGradients`: differentiable
    (once) in h and every parameter of both nets. Check `fused_supported` first."""
    return _apply(f1, f2, h, field=False)


def fused_field(f1, f2, h: torch.Tensor, quads=None, trunk=None, heads=None) -> tuple:
    """(v, v_c, v_s) of the Hamiltonian decoder with scalar nets f1, f2 (paper Eq. (field)) by
    `FusedInputGradients`; differentiable once. `quads` = (A_1, A_2), the kinetic terms'
    matrices (FieldConfig.hnn_quadratic: F_k += h^T S_k h / 2, S_k = (A_k + A_k^T) / 2, so
    grad_h F_k gains S_k h), or None. `trunk` = (weight (W, F), bias (W,)) of a Linear in front
    of the decoder, or None: with it `h` is that Linear's input f (N, F), and the Linear runs
    inside the Function (its backward on the rows with a gradient only). `heads` = (A (K, W),
    a (K,), A_mu' (3, W)), the stacked adapters and the Verlet force's weight, or None: with
    them the result is (v A^T + a, v_c A_mu'^T) alone (`_Heads`: read from g1, g2 and h, v, v_c
    and v_s are not formed). Check `fused_supported` first."""
    return _apply(f1, f2, h, field=True, quads=quads, trunk=trunk, heads=heads)


__all__ = ["ACTIVATION_CODES", "BLOCK_ROWS", "FusedInputGradients", "fused_field",
           "fused_input_gradients", "fused_supported", "net_parameters", "symplectic",
           "symplectic_transpose"]
