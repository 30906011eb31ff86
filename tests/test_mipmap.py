"""Scale-aware anisotropic mipmapping of the hex-plane (docs/design.md section 8, nehad.field.mipmap): the level
formula, the pyramids, trilinear sampling against an independent grid_sample reference, training
gradients, and ONNX parity with the switch on."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import torch.nn.functional as F  # noqa: E402

from nehad.field.config import FieldConfig  # noqa: E402
from nehad.field.hexplane import PLANE_AXES, HexPlane  # noqa: E402
from nehad.field.mipmap import (PlanePyramid, beta_of_rho, build_pyramid, mip_level,  # noqa: E402
                                pool2x, world_axis_sigma)


def test_beta_of_rho_values():
    b = beta_of_rho(torch.tensor([1.0, 2.0, 3.0, 6.0, 1e6]))
    # tanh(rho/3 - 1) / (1 + tanh(rho/3 - 1)) by hand
    want = [math.tanh(r / 3 - 1) / (1 + math.tanh(r / 3 - 1)) for r in (1.0, 2.0, 3.0, 6.0)]
    assert b[:4].tolist() == pytest.approx(want, abs=1e-6)
    assert want[0] == pytest.approx(-1.39680, abs=1e-4) and want[2] == 0.0
    assert want[3] == pytest.approx(0.76159 / 1.76159, abs=1e-5)
    assert float(b[4]) == pytest.approx(0.5, abs=1e-7)  # the limit


def test_mip_level_formula_by_hand():
    cells = torch.tensor([[0.5, 0.5, 0.5],    # below one cell: level 0 on every axis
                          [2.0, 2.0, 2.0],    # isotropic: l = 1 everywhere, L = L_bar
                          [4.0, 1.0, 1.0],    # l = (2, 0, 0): min 0 -> rho = inf, beta = 1/2
                          [4.0, 2.0, 2.0],    # l = (2, 1, 1): rho = 2
                          [8.0, 4.0, 2.0],    # l = (3, 2, 1): rho = 3, beta = 0 -> L
                          [1e4, 1e4, 1e4]])   # clamped to L_max
    got = mip_level(cells, 3).tolist()
    beta2 = math.tanh(2 / 3 - 1) / (1 + math.tanh(2 / 3 - 1))
    want = [0.0, 1.0, 2 - 0.5 * (2 - 2 / 3), 2 - beta2 * (2 - 4 / 3), 3.0, 3.0]
    assert got == pytest.approx(want, abs=1e-5)
    assert want[3] == pytest.approx(2.3159, abs=1e-4)  # beta < 0 pushes it above L (then clamped)
    # the final clamp: l = (3, 1, 1) gives L - beta (L - L_bar) > L_max = 3
    assert float(mip_level(torch.tensor([[8.0, 2.0, 2.0]]), 3)) == 3.0


def test_pool2x_and_pyramid():
    p = torch.arange(2 * 4 * 6, dtype=torch.float32).reshape(1, 2, 4, 6)
    both = pool2x(p)
    assert both.shape == (1, 2, 2, 3)
    assert float(both[0, 0, 0, 0]) == pytest.approx((0 + 1 + 6 + 7) / 4)
    width = pool2x(p, pool_height=False)  # space-time planes: time (height) kept
    assert width.shape == (1, 2, 4, 3) and float(width[0, 1, 3, 2]) == pytest.approx(
        (p[0, 1, 3, 4] + p[0, 1, 3, 5]) / 2)
    odd = pool2x(torch.ones(1, 1, 5, 7))  # floor, like avg_pool2d
    assert odd.shape == (1, 1, 2, 3)
    pyr = build_pyramid(torch.rand(1, 3, 8, 8), 3, True)
    assert [tuple(q.shape[2:]) for q in pyr] == [(8, 8), (4, 4), (2, 2), (1, 1)]
    assert torch.allclose(pyr[3].reshape(3), pyr[0].mean((0, 2, 3)), atol=1e-6)
    assert torch.allclose(pyr[1], F.avg_pool2d(pyr[0], 2), atol=1e-6)


def test_trilinear_sampling_matches_grid_sample_reference():
    torch.manual_seed(0)
    plane = torch.rand(1, 5, 16, 12)
    pyr = PlanePyramid(build_pyramid(plane, 2, True))
    n = 200
    xy = torch.rand(n, 2) * 2.4 - 1.2  # some outside [-1, 1]: border clamp
    level = torch.rand(n) * 2.0
    got = pyr.sample_trilinear(xy, level)
    # independent reference: grid_sample on avg_pool2d levels, blended by hand
    lv = [plane, F.avg_pool2d(plane, 2), F.avg_pool2d(plane, 4)]
    samples = [F.grid_sample(p, xy.reshape(1, 1, n, 2), mode="bilinear", padding_mode="border",
                             align_corners=True)[0, :, 0].T for p in lv]
    lo = level.floor().clamp(max=1).long()
    w = (level - lo).unsqueeze(1)
    ref = torch.stack(samples)  # (3, n, C)
    idx = torch.arange(n)
    want = ref[lo, idx] * (1 - w) + ref[lo + 1, idx] * w
    assert torch.allclose(got, want, atol=1e-6), float((got - want).abs().max())
    # integer levels are plain bilinear samples of that level
    got2 = pyr.sample_trilinear(xy, torch.full((n,), 2.0))
    assert torch.allclose(got2, samples[2], atol=1e-6)


def _hexplane(seed=0):
    torch.manual_seed(seed)
    hp = HexPlane(4, (8, 8, 8, 5), (1, 2))
    with torch.no_grad():
        for scale in hp.planes:
            for p in scale:
                p.uniform_(0.2, 1.0)
    return hp


def test_hexplane_mipmap_limits():
    hp = _hexplane()
    assert hp.mip_levels() == [3, 4]
    n = 64
    x = torch.rand(n, 3) * 2.2 - 1.1
    t = torch.rand(n, 1) * 2 - 1
    hp.requires_grad_(False)
    plain = hp(x, t)
    # footprints far below a cell: level 0, the ordinary grid_sample lookup
    assert torch.allclose(hp(x, t, torch.full((n, 3), 1e-5)), plain, atol=1e-6)
    # footprints far above: the coarsest level; spatial planes are then their mean, space-time
    # planes their mean over the spatial axis, still interpolated along t
    big = hp(x, t, torch.full((n, 3), 100.0))
    want = []
    for scale in hp.planes:
        f = torch.ones(n, hp.out_dim)
        for plane, (a, b) in zip(scale, PLANE_AXES):
            if b == 3:
                col = plane.mean(3, keepdim=True)  # (1, C, T, 1)
                s = F.grid_sample(col, torch.stack([torch.zeros(n), t[:, 0]], 1).reshape(
                    1, 1, n, 2), align_corners=True, padding_mode="border")[0, :, 0].T
            else:
                s = plane.mean((2, 3)).expand(n, -1)
            f = f * s
        want.append(f)
    assert torch.allclose(big, torch.cat(want, 1), atol=1e-5)
    assert float((big - plain).abs().max()) > 1e-2  # the mip path really changes something
    # L_max capped by mipmap_levels
    hp.mipmap_levels = 1
    assert hp.mip_levels() == [1, 1]


def test_world_axis_sigma_rotation():
    ls = torch.log(torch.tensor([[0.1, 0.2, 0.4], [0.1, 0.2, 0.4]]))
    q = torch.tensor([[1.0, 0, 0, 0], [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]])
    s = world_axis_sigma(ls, q * 3.0)  # unnormalised quats are normalised
    assert s[0].tolist() == pytest.approx([0.1, 0.2, 0.4], abs=1e-6)
    assert s[1].tolist() == pytest.approx([0.2, 0.1, 0.4], abs=1e-6)  # 90 deg about z swaps x, y


def _field_model(mipmap: bool, n: int = 600, seed: int = 0):
    """A NeHaD model with a clearly non-identity field and Gaussians whose sizes span every mip
    level (no training: random weights)."""
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel, RunInfo

    cfg = FieldConfig(out_dim=8, resolution=(8, 8, 8, 4), multires=(1, 2), width=16,
                      hnn_hidden=16, mipmap=mipmap)
    g = GaussianParameters.random_in_box(n, sh_degree=1, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        # world scales from 0.01 to 3 (cells: 2.6/7 and 2.6/15): levels 0 .. L_max, anisotropic
        g.log_scales.copy_(torch.empty(n, 3).uniform_(math.log(0.01), math.log(3.0),
                                                      generator=gen))
        g.quats.copy_(torch.randn(n, 4, generator=gen))
        g.t_eq.copy_(torch.rand(n, 1, generator=gen))
    torch.manual_seed(seed)
    field = DeformationField(cfg, torch.tensor([[-1.3] * 3, [1.3] * 3]), 2.6)
    with torch.no_grad():
        for name, p in field.named_parameters():
            if name.startswith("adapters."):
                p.copy_(torch.randn(p.shape, generator=gen) * 0.3)
            elif name.startswith("hexplane."):
                p.add_(torch.randn(p.shape, generator=gen) * 0.5)
    meta = RunInfo(time_range=(0.0, 1.0), background=(1.0, 1.0, 1.0), sh_degree=1,
                   aabb=field.aabb.numpy().astype(np.float64), extent=2.6)
    return NeHaDModel(g, field).eval(), meta


def test_mipmap_levels_spread_and_gradients():
    model, _ = _field_model(True)
    g, field = model.gaussians, model.field
    sigma = world_axis_sigma(g.log_scales, g.quats) * (2.0 / (field.aabb[1] - field.aabb[0]))
    res = field.hexplane.resolutions()[0]
    cells = torch.tensor([(r - 1) * 0.5 for r in res[:3]])
    lv = mip_level(sigma * cells, field.hexplane.mip_levels()[0])
    hist = np.histogram(lv.detach().numpy(), bins=[0, 1e-6, 1, 2, 3.0001])[0]
    print(f"level histogram (0, (0,1), [1,2), [2,3]): {hist.tolist()}")
    assert (hist > 20).all()  # every level range is exercised
    out = model.gaussians_at(0.3)
    loss = out[0].square().sum() + out[1].sum()
    loss.backward()
    plane = field.hexplane.planes[0][0]
    assert plane.grad is not None and float(plane.grad.abs().sum()) > 0
    assert g.log_scales.grad is not None  # through the rendering path, not through the level
    # the mip path changes the deformation against the same weights without it
    plain, _ = _field_model(False)
    plain.field.load_state_dict(model.field.state_dict())
    with torch.no_grad():
        a, b = model.gaussians_at(0.3)[0], plain.gaussians_at(0.3)[0]
    assert float((a - b).abs().max()) > 1e-3


def test_mipmap_onnx_parity(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    onnx = pytest.importorskip("onnx")
    from nehad.export.checks import ALLOWED_OPS, check_graph
    from nehad.export.onnx_export import export_model, parity_error

    model, meta = _field_model(True)
    path = tmp_path / "mip.onnx"
    rep = export_model(model, meta, path, static=False)  # every row through the field
    ops = check_graph(onnx.load(str(path)), full_check=True)
    assert set(ops) <= ALLOWED_OPS and "GridSample" not in ops
    assert {"Log", "Tanh", "Floor", "ReduceMax", "ReduceMin"} <= set(ops)
    # the pyramids are initializers, not pooled in every run: the only means left are L_bar,
    # one per hex-plane scale (pooling would add 2 per spatial plane level, 1 per time plane)
    assert ops["ReduceMean"] == len(model.field.cfg.multires)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = {}
    for t in (0.0, 0.21, 0.5, 0.9, 1.0):
        got = sess.run(None, {"time": np.array([t], np.float32)})
        with torch.no_grad():
            ref = [o.numpy() for o in model.gaussians_at(torch.tensor([t]))]
        ref[4] = ref[4][:, :4]
        for name, a, b in zip(("means", "scales", "quats", "opacities", "sh"), got, ref):
            assert a.shape == b.shape, name
            worst[name] = max(worst.get(name, 0.0), parity_error(a, b))
    print(f"mipmap ONNX parity {worst} (export's own check {rep.parity})")
    assert max(worst.values()) <= 1e-5
    m0 = sess.run(["means"], {"time": np.array([0.0], np.float32)})[0]
    m1 = sess.run(["means"], {"time": np.array([1.0], np.float32)})[0]
    assert np.abs(m0 - m1).max() > 1e-2  # a real deformation


def test_mipmap_config_validation():
    with pytest.raises(ValueError, match="mipmap_levels"):
        FieldConfig(mipmap_levels=-1).validate()
    with pytest.raises(ValueError, match="mipmap"):
        FieldConfig(mipmap="yes").validate()
    assert FieldConfig().mipmap is False  # off by default (docs/design.md section 8)


def test_mipmap_split_layers_parity(tmp_path):
    """Streaming layers with mipmapping on: every prefix of the split export against torch."""
    pytest.importorskip("onnxruntime")
    from nehad.export.layers import export_split_model
    from nehad.export.onnx_export import parity_error
    from nehad.runtime.layers import LayeredModel

    model, meta = _field_model(True, n=500, seed=2)
    meta = meta.replace(layer=np.array([0] * 150 + [1] * 200 + [2] * 150, np.int32))
    rep = export_split_model(model, meta, tmp_path / "layers")
    assert max(rep.parity.values()) <= 1e-5
    for k, n in ((0, 150), (1, 350), (2, 500)):
        lm = LayeredModel(tmp_path / "layers", max_layer=k)
        for t in (0.0, 0.6, 1.0):
            out = lm.outputs(t)
            with torch.no_grad():
                ref = model.gaussians_at(torch.tensor([t]))
            err = max(parity_error(out[name], r.numpy()[:n])
                      for name, r in zip(("means", "scales", "quats", "opacities"), ref))
            assert err <= 1e-5, (k, t, err)


def test_split_export_rejects_layers_out_of_order(tmp_path):
    """The out-of-order error path names the problem (it raised NameError before) and writes
    nothing."""
    from nehad.export.layers import export_split_model
    from nehad.export.onnx_export import ExportError

    model, meta = _field_model(False, n=60, seed=3)
    meta = meta.replace(layer=np.array([0] * 20 + [2] * 20 + [1] * 20, np.int32))
    with pytest.raises(ExportError, match="not stored in order"):
        export_split_model(model, meta, tmp_path / "layers")
    assert not (tmp_path / "layers").exists()
