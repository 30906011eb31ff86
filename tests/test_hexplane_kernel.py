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


@pytest.mark.parametrize("by_scale", [True, False])
@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
@pytest.mark.parametrize("t", [-1.0, -0.31, 0.5, 1.0])
def test_lookup_and_gradients_match_grid_sample(t, layout, by_scale, monkeypatch):
    """Values and gradients (points and planes) against grid_sample, with the backward run per
    scale and as the two passes over points and planes (`backward_by_scale`); a third of the
    rows without an upstream gradient."""
    from nehad.field import hexplane_kernel

    monkeypatch.setattr(hexplane_kernel, "backward_by_scale", lambda n_scales: by_scale)
    hp = _planes()
    x = _points()
    tt = torch.tensor([[t]], dtype=torch.float64)
    x_ref = x.clone().requires_grad_(True)
    ref = hp(x_ref, tt)  # grid_sample in float64
    weight = torch.randn(ref.shape, generator=torch.Generator().manual_seed(2),
                         dtype=torch.float64)
    weight[::3] = 0.0  # rows no pixel sees: left out of the backward
    (ref * weight).sum().backward()
    planes = [p for scale in hp.planes for p in scale]
    planes32 = [p.detach().float().contiguous(memory_format=layout).requires_grad_(True)
                for p in planes]
    x32 = x.float().requires_grad_(True)
    out = hexplane_lookup(torch.cat([x32, tt.float().expand(len(x), 1)], 1), planes32,
                          PLANE_AXES)
    (out * weight.float()).sum().backward()
    assert (out.double() - ref).abs().max() <= 1e-6 * ref.abs().max()
    assert (x32.grad.double() - x_ref.grad).abs().max() <= 1e-5 * x_ref.grad.abs().max()
    for mine, p in zip(planes32, planes):
        assert mine.grad.shape == p.shape
        assert mine.grad.is_contiguous(memory_format=layout)
        assert (mine.grad.double() - p.grad).abs().max() <= 1e-5 * p.grad.abs().max()


def test_the_two_backward_schedules_agree(monkeypatch):
    """Per scale or as two passes (`backward_by_scale`, chosen by the thread count): the same
    float32 gradients. dL/du is summed per scale and each texel gets its points' shares in the
    same order in both, so they have given the same bits in every run but two, both the first
    run after an edit of the kernels' module (some kernels from Numba's cache, others just
    compiled, which rounded differently until 2026-12-03: docs/development.md); the test asks
    for agreement to float32 rounding, which a missing or doubled share would break."""
    from nehad.field import hexplane_kernel

    planes = [p.detach().float().contiguous(memory_format=torch.channels_last)
              for scale in _planes().planes for p in scale]
    u = torch.cat([_points().float(), torch.full((300, 1), 0.3)], 1)
    weight = torch.randn(300, 16, generator=torch.Generator().manual_seed(3))
    weight[::4] = 0.0
    grads = []
    for by_scale in (True, False):
        monkeypatch.setattr(hexplane_kernel, "backward_by_scale", lambda n_scales: by_scale)
        leaves = [u.clone().requires_grad_(True)] + [p.clone().requires_grad_(True)
                                                     for p in planes]
        (hexplane_lookup(leaves[0], leaves[1:], PLANE_AXES) * weight).sum().backward()
        grads.append([x.grad for x in leaves])
    assert grads[0][0].abs().max() > 0
    for a, b in zip(*grads):
        assert (a - b).abs().max() <= 1e-6 * b.abs().max()


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


@pytest.mark.parametrize("by_scale", [True, False])
def test_no_time_gradient_leaves_the_other_gradients_bit_for_bit(by_scale, monkeypatch):
    """`time_grad=False` (a time column nothing learns, as in training) skips dL/dt' alone:
    dL/dx, y, z and the planes' gradients are the same bits as with it, dL/dt' is 0."""
    from nehad.field import hexplane_kernel

    monkeypatch.setattr(hexplane_kernel, "backward_by_scale", lambda n_scales: by_scale)
    planes = [p.detach().float().contiguous(memory_format=torch.channels_last)
              for scale in _planes().planes for p in scale]
    u = torch.cat([_points().float(), torch.linspace(-0.9, 0.9, 300)[:, None]], 1)
    weight = torch.randn(300, 16, generator=torch.Generator().manual_seed(8))
    grads = []
    for time_grad in (True, False):
        leaves = [u.clone().requires_grad_(True)] + [p.clone().requires_grad_(True)
                                                     for p in planes]
        out = hexplane_lookup(leaves[0], leaves[1:], PLANE_AXES, time_grad=time_grad)
        (out * weight).sum().backward()
        grads.append([x.grad for x in leaves])
    assert grads[0][0][:, 3].abs().max() > 0 and grads[1][0][:, 3].abs().max() == 0
    assert torch.equal(grads[0][0][:, :3], grads[1][0][:, :3])
    assert all(torch.equal(a, b) for a, b in zip(grads[0][1:], grads[1][1:]))


def test_the_time_gradient_reaches_a_time_that_asks_for_it():
    """HexPlane asks the kernel for dL/dt' when its time input requires a gradient: dL/dt
    equals grid_sample's (float64 reference)."""
    hp = _planes()
    x = _points()
    t = torch.full((len(x), 1), 0.35, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(len(x), 16, generator=torch.Generator().manual_seed(9),
                         dtype=torch.float64)
    (hp(x, t) * weight).sum().backward()
    fast = hp.float()
    fast.kernel = "numba"
    t32 = t.detach().float().requires_grad_(True)
    out = fast(x.float(), t32)
    assert type(out.grad_fn).__name__.startswith("HexPlaneLookup")
    (out * weight.float()).sum().backward()
    assert (t32.grad.double() - t.grad).abs().max() <= 1e-5 * t.grad.abs().max()


LAYOUTS = [torch.contiguous_format, torch.channels_last]


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("shape", [(1, 8, 6, 5), (1, 32, 64, 64), (1, 3, 2, 9), (1, 4, 3, 2)])
def test_plane_tv_and_gradient_match_autograd(shape, layout):
    """The Numba total variation (nehad.field.hexplane_kernel.plane_tv) against the torch
    function (_tv) and its autograd gradient in float64, scaled by an upstream gradient."""
    from nehad.field.hexplane import _tv
    from nehad.field.hexplane_kernel import plane_tv

    g = torch.Generator().manual_seed(3)
    p = torch.randn(shape, generator=g, dtype=torch.float64, requires_grad=True)
    ref = _tv(p)
    ref.backward()
    q = p.detach().float().contiguous(memory_format=layout).requires_grad_(True)
    value = plane_tv(q)
    (2.5 * value).backward()
    assert abs(float(value.detach()) - float(ref.detach())) <= 1e-6 * float(ref.detach())
    assert (q.grad.double() - 2.5 * p.grad).abs().max() <= 1e-6 * (2.5 * p.grad).abs().max()


def test_plane_smoothness_dispatches_to_the_kernel():
    hp = _planes().float()
    hp.kernel = "numba"
    out = hp.plane_smoothness("tv")
    hp.kernel = "torch"
    ref = hp.plane_smoothness("tv")
    assert "PlaneTV" in repr(out.grad_fn.next_functions)  # through the Numba pass
    assert abs(float(out.detach()) - float(ref.detach())) <= 1e-6 * float(ref.detach())


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("shape", [(1, 8, 6, 5), (1, 32, 25, 64), (1, 3, 3, 9), (1, 2, 2, 4)])
def test_time_regularisers_and_gradients_match_autograd(shape, layout):
    """The Numba space-time regularisers (second difference along t, mean |1 - p|) against the
    torch functions and their autograd gradients in float64, each with its own upstream
    gradient; a plane of two times has no second difference (0, and no gradient from it)."""
    from nehad.field.hexplane import _second_order
    from nehad.field.hexplane_kernel import time_regularisers

    g = torch.Generator().manual_seed(4)
    p = (1.0 + 0.5 * torch.randn(shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    with torch.no_grad():
        p[0, 0, 0, 0] = 1.0  # |1 - p| at its kink: gradient 0, as torch's
    l1 = (1.0 - p).abs().mean()
    second = _second_order(p) if shape[2] > 2 else p.sum() * 0.0
    (0.7 * second + 1.9 * l1).backward()
    q = p.detach().float().contiguous(memory_format=layout).requires_grad_(True)
    s2, s1 = time_regularisers(q)
    (0.7 * s2 + 1.9 * s1).backward()
    assert abs(float(s2.detach()) - float(second.detach())) <= 1e-6 * max(float(second.detach()), 1e-30) + 1e-12
    assert abs(float(s1.detach()) - float(l1.detach())) <= 1e-6 * float(l1.detach())
    assert (q.grad.double() - p.grad).abs().max() <= 1e-6 * p.grad.abs().max()


def test_plane_regularisers_equal_the_per_plane_passes_bit_for_bit():
    """nehad.field.plane_regularisers (one Function over all planes, its gradients views of one
    array laid out as the planes' buffer) against plane_tv and time_regularisers plane by plane:
    the same three values and the same gradients, bit for bit, with three upstream scalars."""
    from nehad.field.hexplane import PLANE_AXES, SPACE_PLANES, TIME_PLANES
    from nehad.field.hexplane_kernel import plane_tv, time_regularisers
    from nehad.field.plane_regularisers import plane_regularisers

    hp = _planes().float()
    with torch.no_grad():
        for p in hp.parameters():
            p.add_(0.2 * torch.randn_like(p))
    planes = [p for scale in hp.planes for p in scale]
    timed = [k in TIME_PLANES for _ in hp.planes for k in range(len(PLANE_AXES))]
    space, time_, l1 = plane_regularisers(planes, timed)
    (0.3 * space + 0.7 * time_ + 1.9 * l1).backward()
    got = [p.grad.clone() for p in planes]
    hp.zero_grad(set_to_none=True)
    ref_space = sum(plane_tv(scale[k]) for scale in hp.planes for k in SPACE_PLANES)
    pairs = [time_regularisers(scale[k]) for scale in hp.planes for k in TIME_PLANES]
    ref_time, ref_l1 = sum(a for a, _ in pairs), sum(b for _, b in pairs)
    (0.3 * ref_space + 0.7 * ref_time + 1.9 * ref_l1).backward()
    for a, b in ((space, ref_space), (time_, ref_time), (l1, ref_l1)):
        assert torch.equal(a.detach(), b.detach())
    for a, p in zip(got, planes):
        assert torch.equal(a, p.grad)
    assert float(space.detach()) > 0 and float(time_.detach()) > 0 and float(l1.detach()) > 0


def test_plane_regularisers_add_into_the_planes_grad_in_place():
    """With `into_grad`, planes that hold a `.grad` get the regularisers' gradients added into
    it (scaled in the same pass), as autograd's addition of the returned ones gives to float
    rounding; a plane without one gets its gradient returned as before."""
    from nehad.field.hexplane import PLANE_AXES, TIME_PLANES
    from nehad.field.plane_regularisers import plane_regularisers

    hp = _planes(seed=12).float()
    planes = [p for scale in hp.planes for p in scale]
    timed = [k in TIME_PLANES for _ in hp.planes for k in range(len(PLANE_AXES))]
    before = [torch.randn(p.shape, generator=torch.Generator().manual_seed(20 + i))
              for i, p in enumerate(planes)]
    results = []
    for into_grad in (False, True):
        for i, (p, b) in enumerate(zip(planes, before)):
            p.grad = None if i == 3 else b.clone()  # plane 3 without one
        space, time_, l1 = plane_regularisers(planes, timed, into_grad=into_grad)
        held = [p.grad for p in planes]
        (0.3 * space + 0.7 * time_ + 1.9 * l1).backward()
        if into_grad:  # in place: the same tensors
            assert all(p.grad is h for i, (p, h) in enumerate(zip(planes, held)) if i != 3)
        results.append([p.grad.clone() for p in planes])
    for ref, mine, b in zip(*results, before):
        assert (ref - b).abs().max() > 0
        assert (mine - ref).abs().max() <= 1e-6 * ref.abs().max()


def test_field_regularisers_match_the_torch_path():
    """DeformationField.regularization_terms: the same three values through the Numba kernels
    as through torch."""
    import numpy as np

    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField

    field = DeformationField(FieldConfig(resolution=(8, 8, 8, 6)), np.array([[-1.0] * 3, [1.0] * 3]), 2.0)
    with torch.no_grad():
        for p in field.hexplane.parameters():
            p.add_(0.2 * torch.randn_like(p))
    field.hexplane.kernel = "numba"
    fast = {k: float(v.detach()) for k, v in field.regularization_terms().items()}
    field.hexplane.kernel = "torch"
    ref = {k: float(v.detach()) for k, v in field.regularization_terms().items()}
    for k in ref:
        assert abs(fast[k] - ref[k]) <= 1e-6 * abs(ref[k]), k


def test_planes_are_stored_channel_last():
    """HexPlane keeps its planes in channel-last memory (the kernels' layout), shape unchanged;
    the layout survives a dtype change and a state dict round trip."""
    hp = HexPlane(4, (5, 6, 7, 3), (1, 2))
    for p in hp.parameters():
        assert p.shape[0] == 1 and p.is_contiguous(memory_format=torch.channels_last)
    other = HexPlane(4, (5, 6, 7, 3), (1, 2))
    other.load_state_dict({k: v.contiguous() for k, v in hp.state_dict().items()})
    for p, q in zip(other.parameters(), hp.parameters()):
        assert torch.equal(p, q) and p.is_contiguous(memory_format=torch.channels_last)
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in hp.double().parameters())


def test_spatial_order_is_the_stable_sort_of_the_cell_keys():
    """The counting sort against numpy's stable argsort of the same keys (x-major cells of
    2 / 32 over [-1, 1]^3, clamped; NaN and -inf in the first cell, +inf in the last)."""
    import numpy as np

    from nehad.field.hexplane_kernel import _spatial_order

    rng = np.random.default_rng(3)
    u = rng.normal(0.0, 0.8, (5000, 4)).astype(np.float32)
    u[:40, :3] = np.round(u[:40, :3] * 16) / 16  # on cell borders
    u[40, 0], u[41, 1], u[42, 2] = np.nan, np.inf, -np.inf
    q = np.nan_to_num((u[:, :3] + 1.0) * 16.0, nan=0.0, posinf=32.0, neginf=0.0)
    q = np.clip(q, 0, 31).astype(np.int64)
    keys = (q[:, 0] * 32 + q[:, 1]) * 32 + q[:, 2]
    assert np.array_equal(_spatial_order(u), np.argsort(keys, kind="stable"))


def test_points_without_gradient_are_left_out_of_the_backward():
    """A third of the points with a zero upstream gradient (Gaussians no pixel sees), and then
    all of them: the gradients equal grid_sample's (float64 reference), the points' own zero."""
    hp = _planes(seed=4)
    x = _points(seed=5)
    tt = torch.tensor([[0.2]], dtype=torch.float64)
    planes = [p for scale in hp.planes for p in scale]
    for zero_rows in (slice(None, None, 3), slice(None)):
        x_ref = x.clone().requires_grad_(True)
        ref = hp(x_ref, tt)
        weight = torch.randn(ref.shape, generator=torch.Generator().manual_seed(6),
                             dtype=torch.float64)
        weight[zero_rows] = 0.0
        for p in planes:
            p.grad = None
        (ref * weight).sum().backward()
        planes32 = [p.detach().float().contiguous(memory_format=torch.channels_last)
                    .requires_grad_(True) for p in planes]
        x32 = x.float().requires_grad_(True)
        out = hexplane_lookup(torch.cat([x32, tt.float().expand(len(x), 1)], 1), planes32,
                              PLANE_AXES)
        (out * weight.float()).sum().backward()
        assert x32.grad[zero_rows].abs().max() == 0
        for mine, p in zip(planes32, planes):
            scale = max(p.grad.abs().max().item(), 1e-30)
            assert (mine.grad.double() - p.grad).abs().max() <= 1e-5 * scale
        if zero_rows == slice(None):
            assert all(mine.grad.abs().max() == 0 for mine in planes32)
        else:
            assert (x32.grad.double() - x_ref.grad).abs().max() <= 1e-5 * x_ref.grad.abs().max()


def test_a_non_finite_coordinate_reads_inside_the_planes():
    """A diverged step's NaN / inf coordinates are read as 0 / +-1 (the kernels index the
    tables with them); the other points are untouched."""
    hp = _planes(seed=7)
    planes = [p.detach().float().requires_grad_(True) for scale in hp.planes for p in scale]
    u = torch.cat([_points(n=20, seed=8).float(), torch.full((20, 1), 0.3)], 1)
    ref = hexplane_lookup(u, planes, PLANE_AXES).detach()
    bad = u.clone()
    bad[3, 0], bad[5, 1], bad[7, 3] = float("nan"), float("inf"), float("-inf")
    out = hexplane_lookup(bad, planes, PLANE_AXES)
    fixed = bad.clone()
    fixed[3, 0], fixed[5, 1], fixed[7, 3] = 0.0, 1.0, -1.0
    assert torch.equal(out.detach(), hexplane_lookup(fixed, planes, PLANE_AXES).detach())
    keep = [i for i in range(20) if i not in (3, 5, 7)]
    assert torch.equal(out.detach()[keep], ref[keep])


def test_gradients_added_in_place_equal_the_returned_ones():
    """With `into_grad`, planes whose `.grad` are views of one flat array (as TrainingAdam
    installs them), already holding a gradient, end with that gradient plus the lookup's, as
    when the lookup returns its gradients for autograd to add; dL/du is the same bits; planes
    with a `.grad` of their own get theirs returned and added by autograd."""
    from nehad.field.hexplane_kernel import gradients_into
    from nehad.optim import _views

    hp = _planes(seed=7).float()
    planes = [p.detach().contiguous(memory_format=torch.channels_last)
              for scale in hp.planes for p in scale]
    u = torch.cat([_points(seed=8).float(), torch.full((300, 1), -0.4)], 1)
    weight = torch.randn(300, 16, generator=torch.Generator().manual_seed(10))
    weight[::5] = 0.0
    before = torch.randn(sum(p.numel() for p in planes),
                         generator=torch.Generator().manual_seed(11))
    results = []
    for into_grad, flat in ((False, True), (True, True), (True, False)):
        leaves = [p.clone().requires_grad_(True) for p in planes]
        grad = before.clone()
        if flat:  # one array in the planes' layout, as TrainingAdam.zero_grad makes it
            for p, view in zip(leaves, _views(grad, leaves)):
                p.grad = view
        else:
            for p, view in zip(leaves, _views(grad, leaves)):
                p.grad = view.clone()
        x = u.clone().requires_grad_(True)
        out = hexplane_lookup(x, leaves, PLANE_AXES, time_grad=False, into_grad=into_grad)
        offsets = torch.tensor([0] + [p.numel() for p in leaves]).cumsum(0).numpy()
        assert (gradients_into(leaves, offsets) is not None) == flat
        (out * weight).sum().backward()
        results.append((x.grad, [p.grad.clone() for p in leaves]))
    reference = results[0]
    start = _views(before, planes)
    assert reference[0].abs().max() > 0
    assert all((r - s).abs().max() > 0 for r, s in zip(reference[1], start))  # it added some
    for grad_x, grads in results[1:]:
        assert torch.equal(grad_x, reference[0])
        for mine, ref in zip(grads, reference[1]):
            assert (mine - ref).abs().max() <= 1e-6 * ref.abs().max()


def test_points_gradient_alone_when_no_plane_needs_one():
    """Planes that need no gradient (fixed, as for the carried objects' Jacobian by the means):
    dL/du is the same bits as with the planes' gradients computed too."""
    planes = [p.detach().float().contiguous(memory_format=torch.channels_last)
              for scale in _planes(seed=13).planes for p in scale]
    u = torch.cat([_points(seed=14).float(), torch.full((300, 1), 0.6)], 1)
    weight = torch.randn(300, 16, generator=torch.Generator().manual_seed(15))
    grads = []
    for planes_grad in (True, False):
        x = u.clone().requires_grad_(True)
        leaves = [p.clone().requires_grad_(planes_grad) for p in planes]
        (hexplane_lookup(x, leaves, PLANE_AXES) * weight).sum().backward()
        grads.append(x.grad)
        assert all((p.grad is None) != planes_grad for p in leaves)
    assert grads[0].abs().max() > 0 and torch.equal(grads[0], grads[1])


def test_fixed_planes_keep_their_grad_under_into_grad():
    """Planes that need no gradient hold on to the `.grad` they have, under `into_grad`: the
    lookup's backward (every plane fixed, a Jacobian by the points) and the regularisers'
    (every other plane fixed) add nothing into it; the others' `.grad` still changes."""
    from nehad.field.hexplane import TIME_PLANES
    from nehad.field.plane_regularisers import plane_regularisers
    from nehad.optim import _views

    planes = [p.detach().float().contiguous(memory_format=torch.channels_last)
              for scale in _planes(seed=16).planes for p in scale]
    before = torch.randn(sum(p.numel() for p in planes),
                         generator=torch.Generator().manual_seed(17))

    def install():  # one flat array, as TrainingAdam.zero_grad installs it
        for p, view in zip(planes, _views(before.clone(), planes)):
            p.grad = view
        return [p.grad.clone() for p in planes]

    held = install()
    x = torch.cat([_points(seed=18).float(), torch.full((300, 1), 0.1)], 1).requires_grad_(True)
    hexplane_lookup(x, planes, PLANE_AXES, time_grad=False, into_grad=True).sum().backward()
    assert x.grad.abs().max() > 0
    assert all(torch.equal(p.grad, h) for p, h in zip(planes, held))
    held = install()
    for k, p in enumerate(planes):
        p.requires_grad_(k % 2 == 0)
    timed = [k in TIME_PLANES for _ in range(2) for k in range(len(PLANE_AXES))]
    sum(plane_regularisers(planes, timed, into_grad=True)).backward()
    for k, (p, h) in enumerate(zip(planes, held)):
        assert torch.equal(p.grad, h) != (k % 2 == 0), k
