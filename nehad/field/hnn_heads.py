"""What runs around the HNN decoder's nets inside its fused pass (`nehad.field.hnn_fused`):
the trunk's Linear in front (`_Trunk`), the adapters and the Verlet force behind (`_Heads`),
and the training path that composes all three with the nets' first layers (`_Composed`,
docs/design.md section 4.4)."""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import torch

from nehad.field.hnn_blocks import (_Nets, _Saved, _backward_block, _blocks, _compact,
                                    _forward_block, _place, _rows_with_gradient, restored)


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
        saved, d1 = _forward_block(self.nets, f, None)
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
                       sums) -> None:
        """grad_f (b, F) = dL/df of a block (0 on its rows without a gradient) from grad (b, J)
        = dL/d[out | force] (contiguous), and the block's share of the sums (`zero_sums`; None:
        no parameter gradients wanted, dL/df alone)."""
        f = saved.acts[0]
        d_weights, d_biases, d_w_out, d_q, d_kw, d_const = sums or [None] * 6
        rows = _rows_with_gradient(grad[None])
        if rows is not None:
            if len(rows) == 0:
                grad_f.zero_()
                return
            saved, grad = _compact(saved, rows), grad.index_select(0, torch.from_numpy(rows))
            f = saved.acts[0]
        saved = restored(self.nets, saved)
        m = grad.shape[0]
        both = grad.expand(2, m, grad.shape[1])
        d_delta = torch.bmm(both, self.q.transpose(1, 2))
        if sums is not None:
            d_q.baddbmm_(saved.deltas[0].transpose(1, 2), both)
        out = grad_f if rows is None else torch.empty((m, grad_f.shape[1]), dtype=grad_f.dtype)
        _backward_block(self.nets, saved, None, out, d_weights, d_biases, d_w_out, d_delta)
        if self.kw is not None:
            out.addmm_(grad, self.kw.T)
            if sums is not None:
                d_kw.addmm_(f.T, grad)
        if sums is not None:
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
                       quadratic: bool, n_params=None) -> tuple:
    """`FusedInputGradients.backward` of the training path (`_Composed`); given `n_params`,
    dL/dx alone (none of the parameters needs a gradient: a Jacobian by the input), with None
    for each of the n_params parameters."""
    tail, n, dtype = composed.tail, xd.shape[0], xd.dtype
    grad = torch.zeros((n, tail.n_out + 3), dtype=dtype)
    for part, u in ((grad[:, :tail.n_out], upstream[0]), (grad[:, tail.n_out:], upstream[1])):
        if u is not None:
            part.copy_(u)
    grad_x = torch.empty(xd.shape, dtype=dtype)
    sums = composed.zero_sums() if n_params is None else None
    for (lo, hi), block in zip(_blocks(n), saved):
        composed.backward_block(block, grad[lo:hi], grad_x[lo:hi], sums)
    if sums is None:
        return (grad_x, None, None, None, None, None, None, *[None] * n_params)
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
