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

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from nehad.field.hnn_blocks import _backward_rows, _blocks, _forward_block, _Nets, _np, _place
from nehad.field.hnn_heads import (_Composed, _composed_backward, _Heads, _Trunk, symplectic,
                                   symplectic_transpose)
from nehad.field.hnn_kernels import ACTIVATION_CODES, _chunks, _field_grads, _field_rows


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

    Forward and backward run block by block (`nehad.field.hnn_blocks.BLOCK_ROWS` rows), so that
    the temporaries of a block stay in the cache between the products and the element-wise
    passes."""

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
            saved.append(_forward_block(nets, hd[lo:hi], g[:, lo:hi])[0])
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
        if composed is not None:  # dL/dx alone where no parameter needs a gradient
            wanted = ctx.needs_input_grad[7:]
            return _composed_backward(composed, saved, xd, upstream, quads is not None,
                                      None if any(wanted) else len(wanted))
        if tail is not None:  # the adapters' and the force's upstream gradients (None: zero)
            g_out, g_force = [None if u is None else u.contiguous() for u in upstream]
            sums = tail.zero_sums()
        else:  # an output nobody used has no gradient: zeros, as autograd would give
            upstream = [torch.zeros((n, width), dtype=dtype) if u is None else u.contiguous()
                        for u in upstream]
        grad_x = torch.empty(xd.shape, dtype=dtype)
        block_rows = max((hi - lo for lo, hi in _blocks(n)), default=0)
        dh_all = torch.empty((block_rows, width), dtype=dtype) if head else None
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


__all__ = ["ACTIVATION_CODES", "FusedInputGradients", "fused_field",
           "fused_input_gradients", "fused_supported", "net_parameters", "symplectic",
           "symplectic_transpose"]
