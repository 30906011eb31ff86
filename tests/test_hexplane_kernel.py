"""The Numba hex-plane lookup (nehad.field.hexplane_kernel) against grid_sample in float64."""

import pytest
import torch

from nehad.field.hexplane import PLANE_AXES, HexPlane
from nehad.field.hexplane_kernel import hexplane_lookup


def _planes(seed=0):
    torch.manual_seed(seed)
    hp = HexPlane(8, (6, 5, 7, 4), (1, 2)).double()
    with torch.no_grad():
        for scale in hp.planes:
            for p in scale:
                p.add_(torch.randn_like(p) * 0.3)
    hp.sample_batches = 1
    return hp


def _points(n=300, seed=1):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2  # some outside the box
    x[:4] = torch.tensor([[-1.0, 1.0, 0.0], [1.0, -1.0, 1.0], [-1.3, 0.2, 1.3], [0.0, 0.0, 0.0]],
                         dtype=torch.float64)  # on the borders, outside, on knots
    return x


@pytest.mark.parametrize("t", [-1.0, -0.31, 0.5, 1.0])
def test_lookup_and_gradients_match_grid_sample(t):
    hp = _planes()
    x = _points()
    tt = torch.tensor([[t]], dtype=torch.float64)
    x_ref = x.clone().requires_grad_(True)
    ref = hp(x_ref, tt)  # grid_sample in float64
    weight = torch.randn(ref.shape, generator=torch.Generator().manual_seed(2),
                         dtype=torch.float64)
    (ref * weight).sum().backward()
    planes = [p for scale in hp.planes for p in scale]
    planes32 = [p.detach().float().requires_grad_(True) for p in planes]
    x32 = x.float().requires_grad_(True)
    out = hexplane_lookup(torch.cat([x32, tt.float().expand(len(x), 1)], 1), planes32,
                          PLANE_AXES)
    (out * weight.float()).sum().backward()
    assert (out.double() - ref).abs().max() <= 1e-6 * ref.abs().max()
    assert (x32.grad.double() - x_ref.grad).abs().max() <= 1e-5 * x_ref.grad.abs().max()
    for mine, p in zip(planes32, planes):
        assert mine.grad.shape == p.shape
        assert (mine.grad.double() - p.grad).abs().max() <= 1e-5 * p.grad.abs().max()


def test_hexplane_dispatches_to_the_kernel_on_cpu_float32():
    hp = _planes().float()
    x = _points().float().requires_grad_(True)
    t = torch.tensor([[0.2]])
    hp.kernel = "numba"
    out = hp(x, t)
    assert type(out.grad_fn).__name__.startswith("HexPlaneLookup")
    hp.kernel = "torch"
    ref = hp(x, t)
    assert (out - ref).abs().max() <= 1e-5
