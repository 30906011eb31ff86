"""NeHaD deformation field (docs/design.md section 4): hex-plane, HNN decoder, adapters, BED, Verlet,
rigidity clamp, switches and the 4DGS baseline decoder."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.field import (  # noqa: E402
    DeformationField, DirectFieldDecoder, FieldConfig, HamiltonianDecoder, HexPlane, ScalarNet,
    atan2_positive_y, bed_masks, clamp_rotation_delta, normalize_aabb, quat_multiply,
    rotation_angle, scalar_net_input_grad, symplectic, time_column)

AABB = [[-1.3, -1.3, -1.3], [1.3, 1.3, 1.3]]
SMALL = dict(out_dim=8, resolution=(8, 8, 8, 5), multires=(1, 2), width=16, hnn_hidden=16)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """These tensors are small: one thread is faster and immune to a busy second core (OpenMP
    barriers under contention made small-tensor steps 20x slower on the 2-core CI box)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def small_cfg(**kw) -> FieldConfig:
    return FieldConfig(**{**SMALL, **kw})


def gaussians(n=64, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    mu = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * 1.2
    s = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 - 3
    q = torch.randn(n, 4, generator=g, dtype=dtype)
    mu_eq = mu + 0.05 * torch.randn(n, 3, generator=g, dtype=dtype)
    t_eq = torch.rand(n, 1, generator=g, dtype=dtype)
    return mu, s, q, mu_eq, t_eq


def randomize_zero_params(module, seed=1, std=0.2):
    """Give the zero-initialised adapters / last layers non-zero values."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            if torch.count_nonzero(p) == 0:
                p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * std)


def quat_to_matrix(q):
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(
        q.shape[:-1] + (3, 3))


def conj(q):
    return q * torch.tensor([1.0, -1, -1, -1], dtype=q.dtype)


# ----------------------------------------------------------------------------- config
@pytest.mark.parametrize("name,value", [
    ("width", 63), ("width", 0), ("depth", 0), ("lam", 1.0), ("lam", -1.2),
    ("activation", "relu"), ("decoder", "transformer"), ("resolution", (64, 64, 64, 1)),
    ("multires", ()), ("gamma", 1.0), ("sigma_t", 0.0), ("sigma_s_fraction", -0.1),
    ("beta", 0.0), ("phi_max", 0.0), ("dt", 0.0), ("hnn_grad", "finite_differences"),
    ("plane_init_high", 0.05), ("hnn_depth", 0), ("spatial_regularizer", "l2"),
    ("verlet", 1), ("norm_eps", 0.0), ("reg_time_l1_weight", -1.0),
])
def test_config_validation_names_the_field(name, value):
    with pytest.raises(ValueError, match=rf"FieldConfig\.{name} "):
        FieldConfig(**{name: value}).validate()


def test_config_relu_error_explains_why_and_presets_round_trip():
    with pytest.raises(ValueError, match="piecewise constant"):
        FieldConfig(activation="relu").validate()
    with pytest.raises(ValueError, match="unknown field"):
        FieldConfig.from_dict({"widht": 64})
    cfg = FieldConfig.preset("hypernerf")
    assert (cfg.out_dim, cfg.resolution, cfg.multires, cfg.width) == (16, (64, 64, 64, 150),
                                                                       (1, 2, 4), 128)
    assert cfg.feature_dim == 48
    assert FieldConfig.from_dict(cfg.to_dict()) == cfg
    d = FieldConfig()
    assert (d.out_dim, d.resolution, d.multires, d.width, d.depth, d.dt) == (
        32, (64, 64, 64, 25), (1, 2), 64, 1, 1.0)
    assert (d.sigma_s_fraction, d.sigma_t, d.beta, d.gamma, d.lam, d.phi_max) == (
        0.1, 0.25, 1.0, 0.05, 0.5, math.pi)


# ----------------------------------------------------------------------------- hex-plane
def _bilinear_reference(plane, u, v):
    """numpy float64 bilinear sample, align_corners=True, border padding."""
    p = plane[0].astype(np.float64)  # (C, H, W)
    _, h, w = p.shape
    x = np.clip((u + 1) / 2 * (w - 1), 0, w - 1)
    y = np.clip((v + 1) / 2 * (h - 1), 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * p[:, y0, x0] + fx * (1 - fy) * p[:, y0, x0 + 1]
            + (1 - fx) * fy * p[:, y0 + 1, x0] + fx * fy * p[:, y0 + 1, x0 + 1]).T


def test_hexplane_matches_bilinear_reference_and_layout():
    torch.manual_seed(0)
    hp = HexPlane(out_dim=4, resolution=(5, 6, 7, 3), multires=(1, 2)).double()
    assert [tuple(p.shape) for p in hp.planes[1]] == [
        (1, 4, 12, 10), (1, 4, 14, 10), (1, 4, 3, 10), (1, 4, 14, 12), (1, 4, 3, 12),
        (1, 4, 3, 14)]  # xy, xz, xt, yz, yt, zt; time resolution not multiplied
    for k, p in enumerate(hp.planes[0]):
        if k in (2, 4, 5):
            assert torch.all(p == 1.0)
        else:
            assert 0.1 <= p.min() and p.max() <= 0.5
    with torch.no_grad():
        for p in hp.parameters():
            p.uniform_(0.5, 1.5)
    x = torch.rand(50, 3, dtype=torch.float64) * 2.4 - 1.2  # some outside [-1, 1]: border
    t = torch.rand(50, 1, dtype=torch.float64) * 2 - 1
    u = torch.cat([x, t], 1).numpy()
    out = hp(x, t).detach().numpy()
    assert out.shape == (50, 8)
    for s, scale in enumerate(hp.planes):
        ref = np.ones((50, 4))
        for p, (a, b) in zip(scale, [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]):
            ref *= _bilinear_reference(p.detach().numpy(), u[:, a], u[:, b])
        np.testing.assert_allclose(out[:, 4 * s:4 * s + 4], ref, rtol=1e-12, atol=1e-12)
    # batched sampling (the CPU speed path) gives the same features for a large N
    xl = torch.rand(20_001, 3, dtype=torch.float64) * 2 - 1
    tl = torch.full((20_001, 1), 0.3, dtype=torch.float64)
    hp.sample_batches = 3
    a = hp(xl, tl)
    hp.sample_batches = 1
    assert torch.allclose(a, hp(xl, tl), rtol=0, atol=1e-14)


def test_normalize_aabb_and_time_mapping():
    box = torch.tensor([[-1.0, 0.0, 2.0], [3.0, 1.0, 6.0]])
    pts = torch.tensor([[-1.0, 0.0, 2.0], [3.0, 1.0, 6.0], [1.0, 0.5, 4.0]])
    assert torch.allclose(normalize_aabb(pts, box),
                          torch.tensor([[-1.0, -1, -1], [1, 1, 1], [0, 0, 0]]))
    # t = 0 reads the first time row, t = 1 the last (2t - 1 spans the whole time axis)
    f = DeformationField(small_cfg(multires=(1,)), AABB, 2.6)
    with torch.no_grad():
        for k in (2, 4, 5):
            f.hexplane.planes[0][k][:, :, 0] = 2.0
            f.hexplane.planes[0][k][:, :, -1] = 3.0
    hp, mu = f.hexplane, gaussians(8)[0]
    x = normalize_aabb(mu, f.aabb)
    with torch.no_grad():
        mid = hp(x, torch.zeros(8, 1))  # t = 0.5 -> middle row, still 1
        assert torch.allclose(hp(x, torch.full((8, 1), -1.0)), 8 * mid)
        assert torch.allclose(hp(x, torch.full((8, 1), 1.0)), 27 * mid)
        col = time_column(0.0, 8, mu)
        assert torch.allclose(f.hexplane(x, 2 * col - 1), 8 * mid)


def test_hexplane_regularisers_real_values():
    hp = HexPlane(out_dim=2, resolution=(6, 6, 6, 5), multires=(1, 2))
    terms = lambda: (hp.plane_smoothness("tv").item(), hp.plane_smoothness("second_order").item(),
                     hp.time_smoothness().item(), hp.time_l1().item())
    with torch.no_grad():
        for scale in hp.planes:
            for k in (0, 1, 3):
                scale[k].fill_(0.3)
    assert terms() == (0.0, 0.0, 0.0, 0.0)  # constant planes, time planes at 1
    with torch.no_grad():
        rows = torch.arange(6, dtype=torch.float32)
        hp.planes[0][0].copy_((0.1 * rows)[:, None].expand(1, 2, 6, 6))  # xy: linear along y
        tau = torch.arange(5, dtype=torch.float32)
        hp.planes[0][2].copy_((1.0 + tau**2)[:, None].expand(1, 2, 5, 6))  # xt: quadratic in t
        hp.planes[1][5].fill_(1.5)  # zt at scale 2
    tv, so, ts, l1 = terms()
    assert tv == pytest.approx(2 * 0.01, rel=1e-5)  # 2 (mean dy^2 + mean dx^2)
    assert so == pytest.approx(0.0, abs=1e-10)  # linear -> no second difference
    assert ts == pytest.approx(4.0, rel=1e-6)  # (d^2/dt^2 tau^2)^2 = 4
    assert l1 == pytest.approx(np.mean(tau.numpy() ** 2) + 0.5, rel=1e-6)
    f = DeformationField(small_cfg(), AABB)
    r = f.regularization_terms()
    assert set(r) == {"plane_smoothness", "time_smoothness", "time_l1"}
    assert r["time_smoothness"].item() == 0.0 and r["time_l1"].item() == 0.0
    weight = f.cfg.reg_plane_weight
    assert weight == 1e-3  # docs/training.md: the default raised from 4DGS's 1e-4
    assert f.regularization_loss().item() == pytest.approx(weight * r["plane_smoothness"].item())


# ----------------------------------------------------------------------------- HNN
@pytest.mark.parametrize("activation", ["tanh", "softplus", "silu"])
def test_hnn_fields_curl_free_and_divergence_free(activation):
    torch.manual_seed(0)
    dec = HamiltonianDecoder(width=12, hidden=16, depth=2, activation=activation).double()
    for _ in range(3):
        h0 = torch.randn(1, 12, dtype=torch.float64)
        jc = torch.autograd.functional.jacobian(lambda h: dec(h).v_c, h0).reshape(12, 12)
        js = torch.autograd.functional.jacobian(lambda h: dec(h).v_s, h0).reshape(12, 12)
        assert torch.allclose(jc, jc.T, atol=1e-12)  # Hessian of F1: curl-free
        assert (jc - jc.T).abs().max() < 1e-12 < jc.abs().max()
        assert abs(torch.trace(js).item()) < 1e-12 < js.abs().max()  # divergence-free
        out = dec(h0)
        g2 = scalar_net_input_grad(dec.f2, h0)
        assert torch.allclose(out.v_s, torch.cat([g2[:, 6:], -g2[:, :6]], 1), atol=1e-14)
        assert abs((out.v_s * g2).sum().item()) < 1e-14  # v_s is tangent to F2's level sets
        assert torch.allclose(out.v, out.v_c + out.v_s, atol=1e-14)
    m = torch.zeros(4, 4, dtype=torch.float64)
    m[:2, 2:], m[2:, :2] = torch.eye(2), -torch.eye(2)
    g = torch.randn(3, 4, dtype=torch.float64)
    assert torch.allclose(symplectic(g), g @ m.T)


@pytest.mark.parametrize("activation", ["tanh", "softplus", "silu"])
@pytest.mark.parametrize("depth", [1, 2, 3])
def test_closed_form_input_gradient_equals_autograd(activation, depth):
    torch.manual_seed(depth)
    net = ScalarNet(10, hidden=7, depth=depth, activation=activation).double()
    h = torch.randn(32, 10, dtype=torch.float64, requires_grad=True)
    auto, = torch.autograd.grad(net(h).sum(), h)
    closed = scalar_net_input_grad(net, h)
    assert (closed - auto).abs().max().item() < 1e-6
    assert (closed - auto).abs().max().item() < 1e-13  # in fact exact up to rounding
    # ... and so are their parameter gradients (what training sees through either path)
    w = torch.randn(32, 10, dtype=torch.float64)
    auto_c, = torch.autograd.grad(net(h).sum(), h, create_graph=True)
    params = list(net.parameters())
    ga = torch.autograd.grad((auto_c * w).sum(), params)
    gc = torch.autograd.grad((scalar_net_input_grad(net, h) * w).sum(), params)
    assert max((a - c).abs().max().item() for a, c in zip(ga, gc)) < 1e-12


@pytest.mark.parametrize("mode", ["fused", "closed_form", "autograd"])
def test_quadratic_term_is_the_gradient_of_its_scalar(mode):
    """field.hnn_quadratic: v_c = grad_h (F1 + h^T A1 h / 2), v_s = grad_h (F2 + h^T A2 h / 2) M^T
    against autograd of the whole scalars; still curl-free / divergence-free; the parameter
    gradients equal between the three ways of computing it."""
    torch.manual_seed(5)
    dec = HamiltonianDecoder(8, 16, 2, "softplus", mode, 3.0, quadratic=True).double()
    with torch.no_grad():
        dec.quad1.normal_()
        dec.quad2.normal_()
    h = torch.randn(6, 8, dtype=torch.float64)
    hh = h.clone().requires_grad_(True)
    f1 = dec.f1(hh) + 0.5 * ((hh @ dec.quad1) * hh).sum(-1)
    f2 = dec.f2(hh) + 0.5 * ((hh @ dec.quad2) * hh).sum(-1)
    g1, = torch.autograd.grad(f1.sum(), hh, retain_graph=True)
    g2, = torch.autograd.grad(f2.sum(), hh)
    out = dec(h)
    assert (out.v_c - g1).abs().max().item() < 1e-12
    assert (out.v_s - symplectic(g2)).abs().max().item() < 1e-12
    assert (dec.quadratic_gradients(h)[0]).abs().max().item() > 0.1  # the term is not idle
    jc = torch.autograd.functional.jacobian(lambda x: dec(x).v_c, h[:1]).reshape(8, 8)
    js = torch.autograd.functional.jacobian(lambda x: dec(x).v_s, h[:1]).reshape(8, 8)
    assert (jc - jc.T).abs().max() < 1e-12 and abs(torch.trace(js).item()) < 1e-12
    w = torch.randn(6, 8, dtype=torch.float64)
    grads = torch.autograd.grad((dec(h).v * w).sum(), [dec.quad1, dec.quad2])
    dec.grad_mode = "autograd"
    ref = torch.autograd.grad((dec(h.clone().requires_grad_(True)).v * w).sum(),
                              [dec.quad1, dec.quad2])
    assert max((a - b).abs().max().item() for a, b in zip(grads, ref)) < 1e-12
    assert min(a.abs().max().item() for a in grads) > 0


def test_quadratic_term_starts_at_zero_and_switches_off():
    cfg = FieldConfig()
    assert cfg.hnn_quadratic is True  # the recipe since 2026-11-27 (docs/design.md 4.3)
    f = DeformationField(cfg, [[-1] * 3, [1] * 3])
    assert f.field.quad1.abs().max() == 0 and f.field.quad2.abs().max() == 0
    off = dataclasses.replace(cfg, hnn_quadratic=False)
    assert DeformationField(off, [[-1] * 3, [1] * 3]).field.quad1 is None


def test_a_run_saved_before_the_kinetic_term_loads_without_it():
    """A run's config saved before `hnn_quadratic` existed (3230e51) trained without it: it must
    load so (its field has no quad tensors), though the default is now on (823ff3e)."""
    from nehad.config import build_config, config_from_dict
    from nehad.configtools import to_dict

    saved = to_dict(build_config("test"))
    assert config_from_dict(saved).field.hnn_quadratic is True  # saved with the key: as saved
    del saved["field"]["hnn_quadratic"]
    old = config_from_dict(saved).field
    assert old.hnn_quadratic is False
    keys = set(DeformationField(old, [[-1] * 3, [1] * 3]).state_dict())
    assert not any("quad" in k for k in keys)


def test_decoder_modes_agree_and_work_without_grad():
    torch.manual_seed(0)
    dec = HamiltonianDecoder(width=16, hidden=16)
    h = torch.randn(100, 16)
    train = dec(h)
    assert train.v.requires_grad  # create_graph: the loss on v trains F1, F2
    with torch.no_grad():
        ng = dec(h)
    assert not ng.v.requires_grad and torch.allclose(ng.v, train.v, atol=1e-6)
    with torch.inference_mode():
        inf = dec(h)
    assert torch.allclose(inf.v.clone(), train.v, atol=1e-6)
    dec.grad_mode = "closed_form"
    assert torch.allclose(dec(h).v, train.v, atol=1e-6)


def test_relu_would_starve_upstream_but_smooth_activation_does_not():
    """Why F1, F2 use tanh (docs/design.md section 4.3): grad_h of a ReLU net has a zero Jacobian in h."""
    torch.manual_seed(0)
    relu = torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.ReLU(),
                               torch.nn.Linear(16, 1)).double()
    tanh = ScalarNet(8, 16, 1, "tanh").double()
    h0 = torch.randn(8, dtype=torch.float64)

    def grad_of(net):
        return lambda h: torch.autograd.grad(net(h).sum(), h, create_graph=True)[0]

    assert torch.autograd.functional.jacobian(grad_of(relu), h0).abs().max() == 0.0
    assert torch.autograd.functional.jacobian(grad_of(tanh), h0).abs().max() > 1e-3


# ----------------------------------------------------------------------------- gradients
def test_gradients_reach_planes_and_trunk_only_through_v():
    torch.manual_seed(0)
    f = DeformationField(small_cfg(), AABB, 2.6)
    mu, s, q, mu_eq, t_eq = gaussians(256)
    # adapter biases alone move the Gaussians but bypass v: nothing upstream gets a gradient
    with torch.no_grad():
        f.adapters.mu.bias.fill_(0.1)
    out = f(mu, s, q, 0.9, mu_eq, t_eq)
    out.means.square().sum().backward()
    assert all(p.grad is None or p.grad.abs().max() == 0 for p in f.hexplane.parameters())
    assert all(p.grad is None or p.grad.abs().max() == 0 for p in f.trunk.parameters())
    f.zero_grad(set_to_none=True)
    # non-zero adapter weights: the loss on the deformed means reaches every plane, every trunk
    # weight and F1, F2 (double backward through v = grad_h F)
    with torch.no_grad():
        f.adapters.mu.weight.normal_(0, 0.1)
    out = f(mu, s, q, 0.9, mu_eq, t_eq)
    out.means.square().sum().backward()
    for name, p in f.named_parameters():
        if name.startswith(("hexplane", "trunk", "field", "adapters.mu")):
            assert p.grad is not None and p.grad.abs().max() > 1e-9, name
    # the closed-form path (export) gives the same gradients
    grads = {n: p.grad.clone() for n, p in f.named_parameters() if p.grad is not None}
    f.zero_grad(set_to_none=True)
    f.set_grad_mode("closed_form")
    f(mu, s, q, 0.9, mu_eq, t_eq).means.square().sum().backward()
    for n, g in grads.items():
        assert torch.allclose(dict(f.named_parameters())[n].grad, g, rtol=1e-4, atol=1e-7), n


def test_small_fit_learns_a_time_dependent_displacement():
    """End to end: the field learns mu'(t) = mu + 0.2 sin(2 pi t) e_x through v."""
    torch.manual_seed(0)
    f = DeformationField(small_cfg(bed_position=False, bed_scale=False), AABB, 2.6)
    mu, s, q, _, _ = gaussians(512)
    # eps 1e-15 as the 3DGS/4DGS trainers: the plane gradients through zero-initialised
    # adapters start near 1e-9, below Adam's default eps, which would freeze the planes.
    opt = torch.optim.Adam([{"params": f.param_groups()["grid"], "lr": 1e-2},
                            {"params": f.param_groups()["decoder"], "lr": 3e-3}], eps=1e-15)
    times = torch.linspace(0, 1, 8)

    def loss_at(t):
        target = mu.clone()
        target[:, 0] += 0.2 * torch.sin(2 * math.pi * t)
        return (f(mu, s, q, float(t)).means - target).square().mean()

    before = sum(loss_at(t).item() for t in times) / len(times)
    for it in range(300):
        loss = loss_at(times[it % 8])
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = sum(loss_at(t).item() for t in times) / len(times)
    expected = (0.04 * torch.sin(2 * math.pi * times) ** 2).mean().item() / 3  # identity start
    assert before == pytest.approx(expected, rel=1e-5)
    assert after < 0.02 * before


# ----------------------------------------------------------------------------- identity
@pytest.mark.parametrize("decoder", ["hnn", "mlp"])
def test_fresh_field_is_the_identity(decoder):
    f = DeformationField(small_cfg(decoder=decoder, deform_opacity_sh=True), AABB, 2.6)
    mu, s, q, mu_eq, t_eq = gaussians(128)
    o, sh = torch.randn(128), torch.randn(128, 16, 3)
    for t in (0.0, 0.37, 1.0, torch.tensor([0.5])):
        out = f(mu, s, q, t, mu_eq, t_eq, o, sh)
        assert torch.equal(out.means, mu)
        assert torch.equal(out.log_scales, s)
        assert torch.equal(out.opacity_logits, o) and torch.equal(out.sh, sh)
        if decoder == "mlp":
            assert torch.equal(out.quats, q)
        else:
            assert torch.allclose(out.quats, q / q.norm(dim=1, keepdim=True), atol=1e-7)


# ----------------------------------------------------------------------------- BED
def test_bed_masks_range_equilibrium_and_value():
    cfg = FieldConfig()
    g = torch.Generator().manual_seed(0)
    mu = torch.randn(1000, 3, generator=g, dtype=torch.float64)
    mu_eq = mu + torch.randn(1000, 3, generator=g, dtype=torch.float64) * 0.5
    t = torch.rand(1000, 1, generator=g, dtype=torch.float64)
    t_eq = torch.rand(1000, 1, generator=g, dtype=torch.float64) * 3 - 1
    m_pos, m_scale = bed_masks(mu, mu_eq, t, t_eq, cfg, extent=2.0)
    for m in (m_pos, m_scale):
        assert m.shape == (1000, 1)
        assert m.min() >= 0.05 and m.max() <= 1.0
    assert m_pos.min() < 0.06  # far from equilibrium -> gamma
    # hand-computed: |mu - mu_eq| = 0.05, sigma_s = 0.1, dd = 0.5; dtau = 0.25 / 0.25 = 1
    a = torch.tensor([[0.03, 0.04, 0.0]], dtype=torch.float64)
    mp, ms = bed_masks(a, torch.zeros_like(a), torch.tensor([[0.75]], dtype=torch.float64),
                       torch.tensor([[0.5]], dtype=torch.float64), cfg, extent=1.0)
    e_st = 0.5 * (0.25 + 1.0) + 0.5 * 0.5 * 1.0
    assert mp.item() == pytest.approx(0.95 * math.exp(-e_st) + 0.05, rel=1e-9)
    assert ms.item() == pytest.approx(0.95 * math.exp(-0.5) + 0.05, rel=1e-12)
    # at equilibrium: masks are 1 and the gradients are finite (safe norm)
    mu = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    mu_eq = mu.detach().clone().requires_grad_(True)
    t_eq = torch.full((5, 1), 0.4, dtype=torch.float64, requires_grad=True)
    m_pos, m_scale = bed_masks(mu, mu_eq, torch.full((5, 1), 0.4, dtype=torch.float64), t_eq,
                               cfg, extent=1.0)
    assert torch.allclose(m_pos, torch.ones_like(m_pos), atol=1e-9, rtol=0)
    assert torch.equal(m_scale, torch.ones_like(m_scale))
    gmu, geq, gt = torch.autograd.grad((m_pos + m_scale).sum(), (mu, mu_eq, t_eq))
    for gr in (gmu, geq, gt):
        assert torch.isfinite(gr).all()
    assert gmu.abs().max() == 0 and geq.abs().max() == 0  # equilibrium is a maximum


def test_bed_floor_on_the_deformation_keeps_every_gaussian_responsive():
    """field.bed_floor=deformation (docs/design.md section 4.7): the blend weight 1 - M lies in
    [gamma, 1]: gamma at equilibrium, not 0, and the masks are the paper's minus gamma."""
    cfg = FieldConfig(bed_floor="deformation")
    a = torch.tensor([[0.03, 0.04, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    t = torch.tensor([[0.75], [0.5]], dtype=torch.float64)
    t_eq = torch.full((2, 1), 0.5, dtype=torch.float64)
    mp, ms = bed_masks(a, torch.zeros_like(a), t, t_eq, cfg, extent=1.0)
    e_st = 0.5 * (0.25 + 1.0) + 0.5 * 0.5 * 1.0  # the hand case of the test above
    assert mp[0].item() == pytest.approx(0.95 * math.exp(-e_st), rel=1e-9)
    assert ms[0].item() == pytest.approx(0.95 * math.exp(-0.5), rel=1e-12)
    assert 1.0 - mp[1].item() == pytest.approx(0.05, abs=1e-9)  # at equilibrium: gamma moves
    assert 1.0 - ms[1].item() == pytest.approx(0.05, abs=1e-12)
    paper = bed_masks(a, torch.zeros_like(a), t, t_eq, FieldConfig(), extent=1.0)
    assert torch.allclose(paper[0] - mp, torch.full_like(mp, 0.05), atol=1e-12, rtol=0)
    assert torch.allclose(paper[1] - ms, torch.full_like(ms, 0.05), atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="bed_floor"):
        FieldConfig(bed_floor="nowhere").validate()


# ----------------------------------------------------------------------------- rigidity
def test_quaternion_product_and_onnx_safe_atan2():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(20, 4, generator=g, dtype=torch.float64), torch.randn(
        20, 4, generator=g, dtype=torch.float64)
    assert torch.allclose(quat_to_matrix(quat_multiply(a, b)),
                          quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-12)
    y = torch.rand(1000, generator=g, dtype=torch.float64) * 3 + 1e-9
    x = torch.randn(1000, generator=g, dtype=torch.float64) * 3
    x[:3] = torch.tensor([0.0, -1.0, 1.0])
    assert torch.allclose(atan2_positive_y(y, x), torch.atan2(y, x), atol=1e-12)


def test_rotation_clamp_bounds_large_rotations():
    phi_max = math.pi / 4
    g = torch.Generator().manual_seed(0)
    q = torch.randn(2000, 4, generator=g, dtype=torch.float64) * 10
    rd = clamp_rotation_delta(q, phi_max)
    assert torch.allclose(rd.dr.norm(dim=1), torch.ones(2000, dtype=torch.float64))
    ang = rotation_angle(rd.dr)
    assert ang.max().item() <= phi_max + 1e-12
    assert ang.max().item() > 0.99 * phi_max  # large deltas saturate near phi_max
    assert torch.allclose(ang, phi_max * torch.tanh(rd.phi / phi_max), atol=1e-9)
    # same axis as q
    axis = q[:, 1:] / q[:, 1:].norm(dim=1, keepdim=True)
    assert torch.allclose(rd.dr[:, 1:] / rd.dr[:, 1:].norm(dim=1, keepdim=True), axis, atol=1e-9)
    # in the field: the rotation between r and r' never exceeds phi_max
    f = DeformationField(small_cfg(phi_max=phi_max), AABB).double()
    randomize_zero_params(f.adapters, std=3.0)
    mu, s, r, mu_eq, t_eq = gaussians(500, dtype=torch.float64)
    out = f(mu, s, r, 0.3, mu_eq, t_eq)
    rel = quat_multiply(conj(r / r.norm(dim=1, keepdim=True)), out.quats)
    ang = rotation_angle(rel)
    assert ang.max().item() <= phi_max + 1e-9 and ang.max().item() > 0.5 * phi_max


def test_rotation_clamp_is_identity_to_first_order():
    phi_max = math.pi / 4
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    axis = axis / axis.norm()
    errs = []
    for phi in (0.02, 0.01):
        q = torch.cat([torch.tensor([math.cos(phi / 2)], dtype=torch.float64),
                       math.sin(phi / 2) * axis])[None] * 1.7  # scale must not matter
        ang = rotation_angle(clamp_rotation_delta(q, phi_max).dr).item()
        errs.append(phi - ang)
        assert errs[-1] / phi**3 == pytest.approx(1 / (3 * phi_max**2), rel=1e-3)  # tanh series
    assert errs[0] / errs[1] == pytest.approx(8.0, rel=1e-3)  # O(phi^3)
    # dg = 0: exactly the identity, finite gradients, d(dr'_xyz)/d(dg) = I / dw
    q = torch.tensor([[2.0, 0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    rd = clamp_rotation_delta(q, phi_max)
    assert torch.allclose(rd.dr, torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64))
    jac = torch.autograd.functional.jacobian(lambda x: clamp_rotation_delta(x, phi_max).dr, q)
    jac = jac.reshape(4, 4)
    assert torch.isfinite(jac).all()
    assert torch.allclose(jac[1:, 1:], 0.5 * torch.eye(3, dtype=torch.float64), atol=1e-6)
    q = torch.tensor([[-1.0, 0.0, 0.0, 0.0]], requires_grad=True)  # float32, dw < 0, dg = 0
    rd = clamp_rotation_delta(q, math.pi)
    rd.dr.sum().backward()
    assert torch.isfinite(rd.dr).all() and torch.isfinite(q.grad).all()


# ----------------------------------------------------------------------------- switches
def _switch_outputs(**kw):
    torch.manual_seed(0)
    # the paper's switches (BED on) unless `kw` says otherwise: each is switched off below
    f = DeformationField(small_cfg(**{"dt": 0.5, "bed_position": True, "bed_scale": True, **kw}),
                         AABB, 2.6).double()
    randomize_zero_params(f, seed=3)
    mu, s, q, mu_eq, t_eq = gaussians(200, seed=5, dtype=torch.float64)
    return f, f(mu, s, q, 0.8, mu_eq, t_eq), (mu, s, q, mu_eq, t_eq)


def test_each_switch_gives_its_simpler_formula():
    f, out, (mu, s, q, mu_eq, t_eq) = _switch_outputs()
    a = out.aux
    # the fused decoder does not form v_c (its kinetic term goes straight into the force):
    # v_c from the decoder on its own, F = A_mu' v_c
    v_c = f.field(f.features(mu, time_column(0.8, len(mu), mu))).v_c
    force = v_c @ f.adapters.mu.weight.T
    assert torch.allclose(a["force"], force)
    m_pos, m_scale = bed_masks(mu, mu_eq, torch.full((200, 1), 0.8, dtype=torch.float64), t_eq,
                               f.cfg, 2.6)
    assert torch.allclose(a["m_pos"], m_pos) and torch.allclose(a["m_scale"], m_scale)
    mu_tilde = mu + 0.5 * a["dmu"] + 0.125 * force
    assert torch.allclose(out.means, mu_tilde * (1 - m_pos) + mu * m_pos, atol=1e-12)
    assert torch.allclose(out.log_scales, s + a["ds"] * (1 - m_scale), atol=1e-12)
    dr = clamp_rotation_delta(a["q"], math.pi).dr
    r_new = quat_multiply(q, dr)
    assert torch.allclose(out.quats, r_new / r_new.norm(dim=1, keepdim=True), atol=1e-12)
    assert (out.means - mu).abs().max() > 1e-3 and (out.log_scales - s).abs().max() > 1e-3

    _, o, _ = _switch_outputs(verlet=False)  # no force term
    assert "force" not in o.aux
    assert torch.allclose(o.means, mu + 0.5 * a["dmu"] * (1 - m_pos), atol=1e-12)
    _, o, _ = _switch_outputs(bed_position=False)  # mu' = mu~
    assert torch.allclose(o.means, mu_tilde, atol=1e-12) and "m_pos" not in o.aux
    assert torch.allclose(o.log_scales, out.log_scales)
    _, o, _ = _switch_outputs(bed_scale=False)  # s' = s + ds
    assert torch.allclose(o.log_scales, s + a["ds"], atol=1e-12)
    assert torch.allclose(o.means, out.means)
    _, o, _ = _switch_outputs(bed_position=False, bed_scale=False, verlet=False)
    assert torch.allclose(o.means, mu + 0.5 * a["dmu"], atol=1e-12)
    ff, o, _ = _switch_outputs(bed_position=False, bed_scale=False)
    ff(mu, s, q, 0.8)  # BED off: mu_eq / t_eq not needed
    with pytest.raises(ValueError, match="mu_eq"):
        f(mu, s, q, 0.8)
    _, o, _ = _switch_outputs(rigidity=False)  # r' = N(r (x) q), unclamped
    r_new = quat_multiply(q, a["q"])
    assert torch.allclose(o.quats, r_new / r_new.norm(dim=1, keepdim=True), atol=1e-12)
    assert not torch.allclose(o.quats, out.quats, atol=1e-3)
    assert torch.allclose(o.means, out.means)


@pytest.mark.parametrize("appearance", [False, True])
def test_adapters_are_each_their_own_linear_map(appearance):
    """The adapters run as one product with their stacked weights; each output is still its
    own Linear of v (random weights, so a swapped split would show)."""
    from nehad.field.adapters import Adapters

    torch.manual_seed(21)
    ad = Adapters(8, appearance, 4).double()
    with torch.no_grad():
        for p in ad.parameters():
            p.normal_()
    v = torch.randn(5, 8, dtype=torch.float64)
    out = ad(v)
    assert torch.allclose(out.dmu, v @ ad.mu.weight.T + ad.mu.bias, atol=1e-12)
    assert torch.allclose(out.ds, v @ ad.scale.weight.T + ad.scale.bias, atol=1e-12)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(out.q, v @ ad.rot.weight.T + ad.rot.bias + identity, atol=1e-12)
    if appearance:
        assert torch.allclose(out.d_opacity, v @ ad.opacity.weight.T + ad.opacity.bias,
                              atol=1e-12)
        sh = (v @ ad.sh.weight.T + ad.sh.bias).reshape(5, 4, 3)
        assert torch.allclose(out.d_sh, sh, atol=1e-12)
    else:
        assert out.d_opacity is None and out.d_sh is None


def test_hnn_off_and_mlp_baseline():
    f, out, (mu, s, q, mu_eq, t_eq) = _switch_outputs(use_hnn=False)
    assert isinstance(f.field, DirectFieldDecoder)
    h0 = out.aux["h"][:1].detach()
    jc = torch.autograd.functional.jacobian(lambda h: f.field(h).v_c, h0).reshape(16, 16)
    assert (jc - jc.T).abs().max() > 1e-3  # no longer curl-free
    assert torch.allclose(out.aux["v"], out.aux["v_c"] + out.aux["v_s"])
    assert "m_pos" in out.aux and "phi" in out.aux  # the rest of NeHaD is unchanged

    f, out, (mu, s, q, mu_eq, t_eq) = _switch_outputs(decoder="mlp")
    assert f.field is None and f.adapters is None
    a = out.aux
    assert set(a) == {"h", "dmu", "ds", "dr"}  # no BED, Verlet or clamp
    assert torch.allclose(out.means, mu + a["dmu"], atol=0)
    assert torch.allclose(out.log_scales, s + a["ds"], atol=0)
    assert torch.allclose(out.quats, q + a["dr"], atol=0)
    assert a["dmu"].abs().max() > 1e-3


def test_time_inputs_param_groups_and_appearance():
    f = DeformationField(small_cfg(deform_opacity_sh=True, sh_coeffs=4), AABB, 2.6)
    randomize_zero_params(f.adapters)
    with torch.no_grad():  # time planes start at 1: make the features depend on t
        for p in f.hexplane.parameters():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(2)) * 0.3)
    mu, s, q, mu_eq, t_eq = gaussians(40)
    o, sh = torch.zeros(40), torch.zeros(40, 4, 3)
    with torch.no_grad():
        ref = f(mu, s, q, 0.25, mu_eq, t_eq, o, sh)
        for t in (torch.tensor(0.25), torch.tensor([0.25]), torch.full((40,), 0.25),
                  torch.full((40, 1), 0.25)):
            assert torch.equal(f(mu, s, q, t, mu_eq, t_eq, o, sh).means, ref.means)
        per = f(mu, s, q, torch.linspace(0, 1, 40), mu_eq, t_eq, o, sh)
        assert not torch.allclose(per.means, ref.means)
    assert ref.opacity_logits.abs().max() > 1e-3 and ref.sh.shape == (40, 4, 3)
    assert ref.sh.abs().max() > 1e-3
    with pytest.raises(ValueError, match="time has 3 elements"):
        f(mu, s, q, torch.zeros(3), mu_eq, t_eq, o, sh)
    with pytest.raises(ValueError, match="aabb"):
        f.set_aabb([[0, 0, 0], [1, 0, 1]])
    groups = f.param_groups()
    assert len(groups["grid"]) == 12  # 2 scales x 6 planes
    ids = [id(p) for g in groups.values() for p in g]
    assert len(ids) == len(set(ids)) == len(list(f.parameters()))
    # state dict round trip keeps aabb and extent
    g = DeformationField(small_cfg(deform_opacity_sh=True, sh_coeffs=4), [[0, 0, 0], [1, 1, 1]])
    g.load_state_dict(f.state_dict())
    assert g.extent.item() == pytest.approx(2.6) and torch.equal(g.aabb, f.aabb)
    with torch.no_grad():
        assert torch.equal(g(mu, s, q, 0.25, mu_eq, t_eq, o, sh).means, ref.means)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # legacy (TorchScript) exporter: fast
def test_field_exports_to_onnx_with_standard_ops(tmp_path):
    """The default (autograd) field switches to the closed-form gradient while exported: only
    standard ops (Gather for the plane lookups, Atan, Where; no GridSample, no Atan2, no gradient
    ops) and parity with torch."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    f = DeformationField(small_cfg(), AABB, 2.6).eval()
    randomize_zero_params(f)
    mu, s, q, mu_eq, t_eq = gaussians(300)

    class AtTime(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.f = f

        def forward(self, time):
            o = self.f(mu, s, q, time, mu_eq, t_eq)
            return o.means, o.log_scales, o.quats

    path = str(tmp_path / "field.onnx")
    torch.onnx.export(AtTime(), (torch.tensor([0.3]),), path, input_names=["time"],
                      opset_version=17, dynamo=False)
    model = onnx.load(path)
    onnx.checker.check_model(model, full_check=True)
    ops = {n.op_type for n in model.graph.node}
    assert {"Gather", "Atan", "Tanh"} <= ops and "Atan2" not in ops and "GridSample" not in ops
    assert all(n.domain in ("", "ai.onnx") for n in model.graph.node)
    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    for t in (0.0, 0.3, 1.0):
        got = sess.run(None, {"time": np.array([t], np.float32)})
        with torch.no_grad():
            ref = AtTime()(torch.tensor([t]))
        for a, b in zip(got, ref):
            assert np.abs(a - b.numpy()).max() < 1e-5


def test_bilinear_gather_equals_grid_sample():
    """The export path of the hex-plane lookup is grid_sample(bilinear, border, align_corners)."""
    import torch.nn.functional as F

    from nehad.field.hexplane import bilinear_gather

    g = torch.Generator().manual_seed(3)
    for h, w in [(7, 5), (25, 64), (2, 2)]:
        plane = torch.randn(1, 4, h, w, generator=g, dtype=torch.float64)
        xy = torch.rand(500, 2, generator=g, dtype=torch.float64) * 2.6 - 1.3  # some outside
        xy[:4] = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, 1.0]])
        ref = F.grid_sample(plane, xy[None, None], mode="bilinear", padding_mode="border",
                            align_corners=True)[0, :, 0].T
        assert torch.allclose(bilinear_gather(plane, xy), ref, atol=1e-12), (h, w)
