"""The fused HNN input gradients (nehad.field.hnn_fused, `field.hnn_grad="fused"`) against the
closed form written with torch ops (nehad.field.hnn.scalar_net_input_grad) and torch's
autograd through it, and the vectorised exp / log1p of nehad.field.vecmath against numpy."""

import numba
import numpy as np
import pytest
import torch

from nehad.field import hnn_blocks
from nehad.field.config import FieldConfig
from nehad.field.hnn import HamiltonianDecoder, ScalarNet, scalar_net_input_grad, symplectic
from nehad.field.hnn_fused import (FusedInputGradients, fused_field, fused_input_gradients,
                                   net_parameters)
from nehad.field.vecmath import KERNEL_FASTMATH, exp_nonpositive, log1p_unit

ACTIVATIONS = ["tanh", "softplus", "silu"]


def _nets(activation, depth, width=10, hidden=7, dtype=torch.float64, seed=0):
    """Two ScalarNets with weights large enough (gain 3) that the activations are curved and
    some pre-activations reach |z| > 10, so both signs' branches and the tails are exercised."""
    torch.manual_seed(seed)
    return tuple(ScalarNet(width, hidden, depth, activation, init_gain=3.0).to(dtype)
                 for _ in range(2))


def _inputs(n=64, width=10, dtype=torch.float64, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, width, generator=g, dtype=dtype) * 1.5).requires_grad_(True)


def _loss_grads(outputs, h, nets, seed=2):
    """Gradients of a random linear loss on (g1, g2) w.r.t. h and every parameter of both nets."""
    g = torch.Generator().manual_seed(seed)
    weights = [torch.randn(o.shape, generator=g, dtype=torch.float64).to(o.dtype)
               for o in outputs]
    loss = sum((o * w).sum() for o, w in zip(outputs, weights))
    params = [h] + net_parameters(nets[0]) + net_parameters(nets[1])
    return torch.autograd.grad(loss, params, allow_unused=True)


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| relative to max |b|."""
    return ((a - b).abs().max() / b.abs().max()).item()


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.parametrize("depth", [1, 2, 3])
def test_fused_equals_closed_form_and_its_autograd_in_float64(activation, depth):
    nets = _nets(activation, depth)
    h = _inputs()
    ref = [scalar_net_input_grad(net, h) for net in nets]
    fused = fused_input_gradients(*nets, h)
    for r, f in zip(ref, fused):
        assert _rel(f, r) < 1e-6
        assert _rel(f, r) < 1e-12  # in fact the same float64 arithmetic up to rounding
    ref_grads = _loss_grads(ref, h, nets)
    fused_grads = _loss_grads(fused, h, nets)
    assert len(fused_grads) == 1 + 2 * (2 * depth + 1)  # h, and W_k, b_k, w_out of both nets
    for r, f in zip(ref_grads, fused_grads):
        assert r.abs().max() > 0
        assert _rel(f, r) < 1e-6
        assert _rel(f, r) < 1e-12


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.parametrize("depth", [1, 2])
def test_fused_field_outputs_equal_the_decoders_in_float64(activation, depth):
    """(v, v_c, v_s) straight from the Function: values and gradients of a loss on all three."""
    nets = _nets(activation, depth, seed=12)
    h = _inputs(seed=13)
    g1, g2 = (scalar_net_input_grad(net, h) for net in nets)
    ref = (g1 + symplectic(g2), g1, symplectic(g2))
    fused = fused_field(*nets, h)
    for r, f in zip(ref, fused):
        assert _rel(f, r) < 1e-12
    for r, f in zip(_loss_grads(ref, h, nets), _loss_grads(fused, h, nets)):
        assert r.abs().max() > 0 and _rel(f, r) < 1e-12


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_kinetic_term_in_the_fused_field_in_float64(activation, monkeypatch):
    """With the kinetic terms' A_1, A_2 (non-symmetric, so the symmetrisation is exercised):
    (v, v_c, v_s) against g_k + S_k h written with torch ops, and the gradients of a loss on all
    three w.r.t. h, both nets and A_1, A_2 against autograd through that; in blocks of 7 rows
    over 30 too."""
    nets = _nets(activation, 2, seed=16)
    h = _inputs(n=30, seed=17)
    gen = torch.Generator().manual_seed(18)
    quads = [torch.randn(10, 10, generator=gen, dtype=torch.float64).requires_grad_(True)
             for _ in range(2)]
    g1, g2 = (scalar_net_input_grad(net, h) for net in nets)
    s1, s2 = (0.5 * (a + a.T) for a in quads)
    v_c, v_s = g1 + h @ s1, symplectic(g2 + h @ s2)
    ref = (v_c + v_s, v_c, v_s)

    def grads(outputs):
        gen = torch.Generator().manual_seed(19)
        loss = sum((o * torch.randn(o.shape, generator=gen, dtype=o.dtype)).sum()
                   for o in outputs)
        return torch.autograd.grad(loss, [h] + net_parameters(nets[0])
                                   + net_parameters(nets[1]) + quads)

    ref_grads = grads(ref)
    for rows in (4096, 7):
        monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", rows)
        fused = fused_field(*nets, h, quads)
        for r, f in zip(ref, fused):
            assert _rel(f, r) < 1e-12
        for r, f in zip(ref_grads, grads(fused)):
            assert r.abs().max() > 0 and _rel(f, r) < 1e-12


def _kinetic_and_gappy_weights(gen):
    """The kinetic terms' A_1, A_2 (10, 10) and three (30, 10) loss weights for the decoder's
    outputs, zero on rows 0-9 and 20-25 (no upstream gradient there), float64."""
    quads = [torch.randn(10, 10, generator=gen, dtype=torch.float64).requires_grad_(True)
             for _ in range(2)]
    weights = [torch.randn(30, 10, generator=gen, dtype=torch.float64) for _ in range(3)]
    for w in weights:
        w[:10] = 0.0
        w[20:26] = 0.0
    return quads, weights


@pytest.mark.parametrize("block_rows", [4096, 7])
def test_rows_without_upstream_gradient_are_skipped_exactly(block_rows, monkeypatch):
    """Rows whose upstream gradient is zero (Gaussians no pixel sees) are left out of the
    backward: the gradients equal the full backward's (float64), whole blocks of such rows
    included (rows 0-9 with blocks of 7)."""
    nets = _nets("softplus", 2, seed=20)
    h = _inputs(n=30, seed=21)
    quads, weights = _kinetic_and_gappy_weights(torch.Generator().manual_seed(22))

    def grads():
        out = fused_field(*nets, h, quads)
        loss = sum((o * w).sum() for o, w in zip(out, weights))
        return torch.autograd.grad(loss, [h] + net_parameters(nets[0])
                                   + net_parameters(nets[1]) + quads)

    monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", block_rows)
    monkeypatch.setattr(hnn_blocks, "COMPACT_BELOW", 0.0)  # every row through the backward
    full = grads()
    monkeypatch.setattr(hnn_blocks, "COMPACT_BELOW", 0.85)
    empty = torch.empty  # every buffer the code allocates starts as NaN: a row it forgets shows
    monkeypatch.setattr(torch, "empty", lambda *a, **k: empty(*a, **k).fill_(float("nan")))
    calls = []
    compact = hnn_blocks._compact
    monkeypatch.setattr(hnn_blocks, "_compact", lambda *a: calls.append(1) or compact(*a))
    skipped = grads()
    assert calls  # the rows were gathered
    for r, f in zip(full, skipped):
        assert r.abs().max() > 0 and _rel(f, r) < 1e-12
    assert skipped[0][:10].abs().max() == 0 and skipped[0][20:26].abs().max() == 0


def test_rows_in_several_blocks(monkeypatch):
    """Blocks of 7 rows over 30 (the last one short): the same values and gradients."""
    nets = _nets("silu", 2, seed=10)
    h = _inputs(n=30, seed=11)
    ref = fused_input_gradients(*nets, h)
    ref_grads = _loss_grads(ref, h, nets)
    monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", 7)
    assert len(hnn_blocks._blocks(30)) == 5
    blocked = fused_input_gradients(*nets, h)
    for r, f in zip(list(ref) + list(ref_grads), list(blocked) + list(_loss_grads(blocked, h, nets))):
        assert _rel(f, r) < 1e-12
    field_ref = fused_field(*nets, h.detach())
    monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", 4096)
    for r, f in zip(fused_field(*nets, h.detach()), field_ref):
        assert _rel(f, r) < 1e-12


def test_bits_do_not_depend_on_the_number_of_threads():
    """The row ranges of the kernels (and so the order of the bias gradients' sums) are fixed:
    float32 results are bit for bit the same on 1 and 2 Numba threads."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("Numba was started with 1 thread")
    nets = tuple(net.float() for net in _nets("softplus", 2, width=16, hidden=16, seed=14))
    h = _inputs(n=3000, width=16, dtype=torch.float32, seed=15)
    before = numba.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            out = fused_field(*nets, h)
            results.append(list(out) + list(_loss_grads(out, h, nets)))
    finally:
        numba.set_num_threads(before)
    for a, b in zip(*results):
        assert torch.equal(a, b)


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_gradcheck_on_a_tiny_case(activation):
    nets = _nets(activation, 2, width=4, hidden=3, seed=3)
    h = _inputs(n=5, width=4, seed=4)
    params = [p.detach().clone().requires_grad_(True)
              for net in nets for p in net_parameters(net)]

    quads = [torch.randn(4, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(k))
             .requires_grad_(True) for k in (5, 6)]
    gen = torch.Generator().manual_seed(7)  # a trunk Linear(3, 4) in front: x = f (5, 3)
    f = torch.randn(5, 3, dtype=torch.float64, generator=gen).requires_grad_(True)
    trunk = [torch.randn(4, 3, dtype=torch.float64, generator=gen).requires_grad_(True),
             torch.randn(4, dtype=torch.float64, generator=gen).requires_grad_(True)]
    heads = [torch.randn(*shape, dtype=torch.float64, generator=gen).requires_grad_(True)
             for shape in ((5, 4), (5,), (3, 4))]  # adapters (K = 5) and force behind it
    for field, quadratic, head, tail in ((False, False, False, False), (True, False, False, False),
                                         (True, True, False, False), (True, True, True, False),
                                         (True, True, False, True), (True, False, True, True),
                                         (True, True, True, True)):
        def fn(x, *params):
            out = FusedInputGradients.apply(x, {"tanh": 0, "softplus": 1, "silu": 2}[activation],
                                            True, field, quadratic, head, tail, *params)
            return out  # with the heads: (v A^T + a, v_c A_mu'^T), the kinetic terms folded in

        inputs = (f if head else h, *params, *(quads if quadratic else ()),
                  *(trunk if head else ()), *(heads if tail else ()))
        assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_one_output_unused_and_depth_one_single_row():
    """A loss on g2 alone (g1's upstream gradient is zero) and a single Gaussian."""
    nets = _nets("softplus", 1, seed=5)
    h = _inputs(n=1, seed=6)
    ref = _loss_grads([scalar_net_input_grad(nets[1], h)], h, nets)
    fused = _loss_grads([fused_input_gradients(*nets, h)[1]], h, nets)
    assert all(r is None for r in ref[1:4])  # the reference never touches F1
    assert all(f.abs().max() == 0 for f in fused[1:4])  # the fused backward gives F1 zeros
    for r, f in zip(ref[4:] + ref[:1], fused[4:] + fused[:1]):
        assert r.abs().max() > 0 and torch.allclose(f, r, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_float32_kernels_against_float64(activation):
    """The float32 kernels (vecmath's polynomials, float32 products and sums over 64 units)
    against the float64 closed form: float32 rounding (6e-8 per operation) accumulates over the
    64-term sums and the two layers to about 1e-6 of the largest entry (torch's own float32
    closed form is off by the same 0.3e-6 .. 1.2e-6 here); 1e-5 leaves room, and any wrong term
    of the formula is off by O(1)."""
    nets64 = _nets(activation, 2, width=64, hidden=64, seed=7)
    h64 = _inputs(n=500, width=64, seed=8)
    nets32 = tuple(ScalarNet(64, 64, 2, activation).float() for _ in range(2))
    for n32, n64 in zip(nets32, nets64):
        n32.load_state_dict({k: v.float() for k, v in n64.state_dict().items()})
    h32 = h64.detach().float().requires_grad_(True)
    ref = [scalar_net_input_grad(net, h64) for net in nets64]
    fused = fused_input_gradients(*nets32, h32)
    for r, f in zip(ref, fused):
        assert f.dtype == torch.float32
        assert _rel(f.double(), r) < 1e-5
    for r, f in zip(_loss_grads(ref, h64, nets64), _loss_grads(fused, h32, nets32)):
        assert _rel(f.double(), r) < 1e-5


@numba.njit(fastmath=KERNEL_FASTMATH)
def _special(x, exp_out, log_out):
    for i in range(x.shape[0]):
        t = exp_nonpositive(-abs(x[i]))
        exp_out[i] = t
        log_out[i] = log1p_unit(t)


def test_vectorised_exp_and_log1p():
    x = np.concatenate([np.linspace(0.0, 87.3, 200001), [0.0, 1e-30, 1e-7, 1e-3, 20.0, 87.33]])
    # a few ulp: float32's is 6e-8, float64's 1.1e-16 (numba's exp and numpy's differ by one ulp
    # on some CPUs: AVX-512 znver5)
    for dtype, tol in ((np.float32, 3e-7), (np.float64, 1e-15)):
        xs = x.astype(dtype)
        e, lg = np.empty_like(xs), np.empty_like(xs)
        _special(xs, e, lg)
        exact_e = np.exp(-xs.astype(np.float64))
        exact_lg = np.log1p(e.astype(np.float64))
        assert np.max(np.abs(e / exact_e - 1.0)) <= tol
        assert np.max(np.abs(lg / exact_lg - 1.0)) <= tol
    big = np.array([88.0, 100.0, 1e30], np.float32)  # clamped at exp(-87.33): no 0, no denormal
    e, lg = np.empty_like(big), np.empty_like(big)
    _special(big, e, lg)
    assert np.all(e >= np.finfo(np.float32).tiny) and np.all(e < 1.2e-38)


def _decoders(activation="softplus", quadratic=False):
    torch.manual_seed(9)
    fused = HamiltonianDecoder(12, 8, 2, activation, "fused", init_gain=3.0, quadratic=quadratic)
    closed = HamiltonianDecoder(12, 8, 2, activation, "closed_form", init_gain=3.0,
                                quadratic=quadratic)
    if quadratic:  # non-zero (and non-symmetric) kinetic terms
        with torch.no_grad():
            fused.quad1.copy_(torch.randn(12, 12))
            fused.quad2.copy_(torch.randn(12, 12))
    closed.load_state_dict(fused.state_dict())
    return fused, closed


@pytest.mark.parametrize("quadratic", [False, True])
def test_decoder_fused_mode_in_training_no_grad_and_inference(quadratic):
    fused, closed = _decoders(quadratic=quadratic)
    h = torch.randn(40, 12)
    ref = closed(h)
    out = fused(h)
    assert out.v.requires_grad
    assert out.v.grad_fn is not None and "Fused" in type(out.v_c.grad_fn).__name__
    for a, b in zip(out, ref):
        assert torch.allclose(a, b, atol=1e-6)
    (out.v.square().sum() + out.v_c.sum()).backward()
    (ref.v.square().sum() + ref.v_c.sum()).backward()
    for (name, p), q in zip(fused.named_parameters(), closed.parameters()):
        assert torch.allclose(p.grad, q.grad, rtol=1e-4, atol=1e-6), name
    with torch.no_grad():
        ng = fused(h)
    with torch.inference_mode():
        inf = fused(h)
    assert not ng.v.requires_grad and torch.allclose(ng.v, ref.v, atol=1e-6)
    assert torch.allclose(inf.v.clone(), ref.v, atol=1e-6)


def test_capture_and_unsupported_inputs_take_the_closed_form():
    fused, closed = _decoders()
    h = torch.randn(10, 12)
    traced = torch.jit.trace(fused, h, check_trace=False)
    kinds = {node.kind() for node in traced.graph.nodes()}
    assert "prim::PythonOp" not in kinds  # no autograd Function in the captured graph
    assert "aten::sigmoid" in kinds
    assert torch.allclose(traced(h)[0], closed(h).v, atol=1e-6)
    half = HamiltonianDecoder(12, 8, 2, "softplus", "fused").bfloat16()
    out = half(torch.randn(10, 12, dtype=torch.bfloat16))
    assert out.v.dtype == torch.bfloat16 and "Fused" not in type(out.v_c.grad_fn).__name__


def test_config_accepts_fused():
    assert FieldConfig(hnn_grad="fused").validate().hnn_grad == "fused"
    with pytest.raises(ValueError, match="hnn_grad"):
        FieldConfig(hnn_grad="fast").validate()


def test_rows_with_gradient_are_the_rows_with_a_nonzero_entry(monkeypatch):
    """`_rows_with_gradient` against a hand-made block: a row counts when either net's
    gradient has an entry that is not zero (a NaN counts, -0.0 does not); with too many such
    rows (hnn_blocks.COMPACT_BELOW) it gives None (the full backward)."""
    grads = torch.zeros((2, 9, 4), dtype=torch.float32)
    grads[0, 1, 3] = 2.0
    grads[1, 4, 0] = -1e-30
    grads[0, 6, 2] = float("nan")
    grads[1, 7, 1] = -0.0
    rows = hnn_blocks._rows_with_gradient(grads)
    assert rows.dtype == np.int64 and rows.tolist() == [1, 4, 6]
    monkeypatch.setattr(hnn_blocks, "COMPACT_BELOW", 3 / 9)  # 3 rows of 9 are not fewer
    assert hnn_blocks._rows_with_gradient(grads) is None


@pytest.mark.parametrize("block_rows", [4096, 7])
def test_trunk_inside_equals_trunk_in_front(block_rows, monkeypatch):
    """fused_field with the trunk's Linear inside (`trunk`) against the Linear applied first and
    then fused_field (float64): the same values, and the same gradients for f, the trunk's
    weight and bias, both nets and the kinetic terms, with rows whose upstream gradient is zero
    (rows 0-9 and 20-25: whole blocks of 7 included), every new buffer pre-filled with NaN."""
    nets = _nets("softplus", 2, seed=30)
    gen = torch.Generator().manual_seed(31)
    f = torch.randn(30, 6, dtype=torch.float64, generator=gen).requires_grad_(True)
    lin = torch.nn.Linear(6, 10).double()
    quads, weights = _kinetic_and_gappy_weights(gen)
    wanted = [f, lin.weight, lin.bias] + net_parameters(nets[0]) + net_parameters(nets[1]) + quads

    def run(inside: bool):
        out = (fused_field(*nets, f, quads, (lin.weight, lin.bias)) if inside
               else fused_field(*nets, lin(f), quads))
        loss = sum((o * w).sum() for o, w in zip(out, weights))
        return out, torch.autograd.grad(loss, wanted)

    monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", block_rows)
    ref_out, ref_grads = run(False)
    empty = torch.empty
    monkeypatch.setattr(torch, "empty", lambda *a, **k: empty(*a, **k).fill_(float("nan")))
    out, grads = run(True)
    for r, o in zip(ref_out, out):
        assert _rel(o, r) < 1e-12
    for r, g in zip(ref_grads, grads):
        assert r.abs().max() > 0 and _rel(g, r) < 1e-12
    assert grads[0][:10].abs().max() == 0 and grads[0][20:26].abs().max() == 0


def test_decoder_fused_features_fuses_trunk_and_adapters(monkeypatch):
    """HamiltonianDecoder.fused_features(f, trunk, adapters) against the same modules one
    after the other in closed form (float64, blocks of 5 over 12 rows): the adapters' outputs
    and the force (trunk, first layers and heads composed, hnn_heads._Composed), and the
    gradients of a loss on the last two for f and every
    parameter, with rows 0-4 and 8 out of the loss (a whole block included)."""
    from nehad.field.adapters import Adapters

    torch.manual_seed(32)
    f = torch.randn(12, 6, dtype=torch.float64, requires_grad=True)
    trunk = torch.nn.Linear(6, 8).double()
    adapters = Adapters(8).double()
    with torch.no_grad():
        for p in adapters.parameters():
            p.normal_()
    dec = HamiltonianDecoder(8, 5, 2, "softplus", grad_mode="fused", quadratic=True).double()
    with torch.no_grad():
        dec.quad1.normal_()
        dec.quad2.normal_()
    ref_dec = HamiltonianDecoder(8, 5, 2, "softplus", grad_mode="closed_form",
                                 quadratic=True).double()
    ref_dec.load_state_dict(dec.state_dict())
    weights = torch.randn(12, 13, dtype=torch.float64)
    weights[:5] = 0.0
    weights[8] = 0.0
    monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", 5)

    def run(decoder):
        if decoder is dec:
            fo, ad, force = decoder.fused_features(f, trunk, adapters)
            assert fo is None  # v, v_c, v_s are not formed
        else:
            fo = decoder(trunk(f))
            ad, force = adapters(fo.v), adapters.force(fo.v_c)
        out = torch.cat([ad.dmu, ad.ds, ad.q, force], dim=1)
        params = [f, *trunk.parameters(), *adapters.parameters(), *decoder.parameters()]
        return [out], torch.autograd.grad((out * weights).sum(), params)

    (ref_vals, ref_grads), (vals, grads) = run(ref_dec), run(dec)
    for a, b in zip(vals, ref_vals):
        assert _rel(a, b) < 1e-12
    for a, b in zip(grads, ref_grads):
        assert b.abs().max() > 0 and _rel(a, b) < 1e-12
    assert grads[0][:5].abs().max() == 0 and grads[0][8].abs().max() == 0
    assert ref_dec.fused_features(f, trunk, adapters) is None  # closed form: not fused


@pytest.mark.parametrize("depth", [1, 2])
def test_input_gradient_alone_when_no_parameter_needs_one(depth, monkeypatch):
    """The training path's fused decoder with every parameter fixed (requires_grad False, as
    for the carried objects' Jacobian by the means, nehad.placement): dL/df is the same bits as
    with the parameters' gradients computed too, and the parameters get none."""
    from nehad.field.adapters import Adapters

    torch.manual_seed(33)
    trunk = torch.nn.Linear(6, 8)
    adapters = Adapters(8)
    with torch.no_grad():
        for p in adapters.parameters():
            p.normal_()
    dec = HamiltonianDecoder(8, 5, depth, "softplus", grad_mode="fused", quadratic=True)
    with torch.no_grad():
        dec.quad1.normal_()
        dec.quad2.normal_()
    modules = (trunk, adapters, dec)
    weights = torch.randn(12, 13)
    weights[3] = 0.0
    monkeypatch.setattr(hnn_blocks, "BLOCK_ROWS", 5)
    grads = []
    for fixed in (False, True):
        for m in modules:
            m.requires_grad_(not fixed)
            m.zero_grad(set_to_none=True)
        f = torch.randn(12, 6, generator=torch.Generator().manual_seed(34), requires_grad=True)
        _, ad, force = dec.fused_features(f, trunk, adapters)
        out = torch.cat([ad.dmu, ad.ds, ad.q, force], dim=1)
        (out * weights).sum().backward()
        grads.append(f.grad)
        assert all((p.grad is None) == fixed for m in modules for p in m.parameters())
    assert grads[0].abs().max() > 0 and torch.equal(grads[0], grads[1])
