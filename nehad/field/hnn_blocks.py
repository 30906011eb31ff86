"""One block of rows of the HNN decoder's fused pass (`nehad.field.hnn_fused`, whose docstring
has the closed form and its backward): the two scalar nets' parameters stacked as the kernels
read them (`Nets`), a block's forward (`forward_block`) and what its backward reads (`Saved`),
the backward (`backward_block`), and the backward on a block's rows with a gradient only
(`backward_rows`). The matrix products are torch's (BLAS, batched over the two nets), the
element-wise work between two products `nehad.field.hnn_kernels`' passes."""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import torch

from nehad.field.hnn_kernels import (_chunks, _delta_backward, _hidden_backward, _hidden_layer,
                                     _last_backward, _last_delta, _last_layer, live_rows,
                                     _product)

#: Rows per block of the forward and the backward: a block's (2, rows, 64) float32 temporaries
#: are 1 MB each and stay in the cache between a product and the pass that reads them. The
#: decoder's forward + backward at 10k rows, 1 thread, paired: 101 ms unblocked, 60-67 ms with
#: blocks of 1536 .. 4096 rows, 73 ms with 1024, 82 ms with 512 (docs/performance.md).
BLOCK_ROWS = 2048


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
    """What the backward of one block of rows reads (module docstring's names, per layer). The
    last layer's d_L, e_L and delta_L are not kept (None): the backward computes them again
    from its z_L on the rows it runs on (`restored`), which reads a third of the memory the
    three arrays took (the forward wrote them for every row, the backward read them back for
    about half, long after they had left the cache)."""

    acts: list  # a_0 = h, a_1, ..., a_{L-1}
    derivs: list  # d_k (d_L None until `restored`)
    curvs: list  # e_k (e_L None until `restored`)
    us: list  # u_k, k < L (None for k = L)
    deltas: list  # delta_k (delta_L None until `restored`)
    z_last: torch.Tensor  # z_L without its bias (2, b, H)


def _layer_input(acts: list, k: int) -> torch.Tensor:
    """(2, b, in): what layer k of both nets reads, a_k (h shared by both nets for k = 0)."""
    a = acts[k]
    return a.expand(2, *a.shape) if k == 0 else a


def _forward_block(nets: _Nets, h: torch.Tensor, g: Optional[torch.Tensor]):
    """(what the backward reads, delta_1) for a block of rows h (b, W); g[i] = grad_h F_i(h)
    into g (2, b, W), views of the output, or g None: not formed (`_Composed` reads delta_1
    instead)."""
    b = h.shape[0]
    chunks = _chunks(b)
    acts, derivs, curvs = [h], [], []
    for k in range(nets.depth - 1):
        z = torch.bmm(_layer_input(acts, k), nets.weights[k].transpose(1, 2))
        a, d, e = torch.empty_like(z), torch.empty_like(z), torch.empty_like(z)
        _hidden_layer(nets.kind, _np(z), nets.biases[k], _np(a), _np(d), _np(e), nets.one,
                      chunks)
        acts.append(a)
        derivs.append(d)
        curvs.append(e)
    z_last = torch.bmm(_layer_input(acts, nets.depth - 1), nets.weights[-1].transpose(1, 2))
    deltas = [None] * nets.depth
    deltas[-1] = torch.empty_like(z_last)
    _last_delta(nets.kind, _np(z_last), nets.biases[-1], nets.w_out, _np(deltas[-1]), nets.one,
                chunks)
    us = [None] * nets.depth
    for k in range(nets.depth - 2, -1, -1):
        us[k] = _per_net(deltas[k + 1], nets.weights[k + 1])
        deltas[k] = torch.empty_like(us[k])
        _product(_np(derivs[k]), _np(us[k]), _np(deltas[k]), chunks)
    if g is not None:
        torch.bmm(deltas[0], nets.weights[0], out=g)
    delta_1 = deltas[0]
    deltas[-1] = None  # not kept: `restored`
    return _Saved(acts, derivs + [None], curvs + [None], us, deltas, z_last), delta_1


def restored(nets: _Nets, saved: _Saved) -> _Saved:
    """`saved` with the last layer's d_L, e_L and delta_L computed again from z_L (the same
    values the forward computed: the same kernel code on the same inputs)."""
    z = saved.z_last
    d, e, delta = torch.empty_like(z), torch.empty_like(z), torch.empty_like(z)
    _last_layer(nets.kind, _np(z), nets.biases[-1], nets.w_out, _np(d), _np(e), _np(delta),
                nets.one, _chunks(z.shape[1]))
    return saved._replace(derivs=saved.derivs[:-1] + [d], curvs=saved.curvs[:-1] + [e],
                          deltas=saved.deltas[:-1] + [delta])


def _backward_block(nets: _Nets, saved: _Saved, grads, grad_h: torch.Tensor, d_weights: list,
                    d_biases: np.ndarray, d_w_out: np.ndarray,
                    d_delta: Optional[torch.Tensor] = None) -> None:
    """For one block of rows: grad_h (b, W) = dL/dh of the block, and the block's share of the
    parameters' gradients added to d_weights (W_k's, (2, H, in)), d_biases (L, 2, H) and
    d_w_out (2, H) (d_weights None: no parameter gradients); grads (2, b, W) = (dL/dg1,
    dL/dg2) of the block. Or, given `d_delta` = dL/ddelta_1 (2, b, H) instead of grads
    (`_Composed`, where g is not formed), from there on: d_weights[0] then gets only the first
    layer's input side, dz^T h."""
    acts, derivs, curvs, us, deltas, _ = saved
    h, depth = acts[0], nets.depth
    b, hidden = h.shape[0], nets.weights[0].shape[1]
    chunks = _chunks(b)
    parts = np.empty((chunks, 2, hidden), dtype=nets.w_out.dtype)
    weights = d_weights is not None
    if d_delta is None:
        d_delta = torch.bmm(grads, nets.weights[0].transpose(1, 2))
        if weights:
            d_weights[0].baddbmm_(deltas[0].transpose(1, 2), grads)
    partial = [None] * depth  # P_k
    for k in range(depth - 1):
        du, p = torch.empty_like(d_delta), torch.empty_like(d_delta)
        _delta_backward(_np(d_delta), _np(derivs[k]), _np(us[k]), _np(curvs[k]), _np(du),
                        _np(p), chunks)
        partial[k] = p
        if weights:
            d_weights[k + 1].baddbmm_(deltas[k + 1].transpose(1, 2), du)
        d_delta = _per_net(du, nets.weights[k + 1].transpose(1, 2))
    dz = torch.empty_like(d_delta)
    dw_parts = np.empty_like(parts)
    _last_backward(_np(d_delta), _np(derivs[-1]), _np(curvs[-1]), nets.w_out, _np(dz),
                   dw_parts, parts, chunks)
    if weights:
        d_w_out += dw_parts.sum(axis=0)
    for k in range(depth - 1, -1, -1):
        if weights:
            d_biases[k] += parts.sum(axis=0)
            d_weights[k].baddbmm_(dz.transpose(1, 2), _layer_input(acts, k))
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
    live_rows(_np(grads), live, _chunks(grads.shape[1]))
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
                  pick(saved.curvs, 1), pick(saved.us, 1), pick(saved.deltas, 1),
                  saved.z_last.index_select(1, index))


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
    block = restored(nets, block)
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


def _blocks(n: int):
    """The row blocks (lo, hi) of `BLOCK_ROWS` rows."""
    return [(lo, min(n, lo + BLOCK_ROWS)) for lo in range(0, n, BLOCK_ROWS)]
