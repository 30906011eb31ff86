"""The training optimizer (nehad.optim.TrainingAdam): the hex-plane planes updated as one flat
array give the bits of torch's fused Adam updating them plane by plane."""

from __future__ import annotations

import io

import pytest

torch = pytest.importorskip("torch")

from nehad.field.hexplane import HexPlane  # noqa: E402
from nehad.optim import TrainingAdam  # noqa: E402


def _planes(seed: int):
    torch.manual_seed(seed)
    return list(HexPlane(8, (6, 5, 7, 4), (1, 2)).parameters())


def _set_grads(planes, k: int) -> None:
    """Random gradients through autograd, which lays each out as its plane (channel-last)."""
    gen = torch.Generator().manual_seed(100 + k)
    loss = sum((p * torch.randn(p.shape, generator=gen)).sum() for p in planes)
    loss.backward()


def _run(optimizer_type, steps: int, reload_at: int | None = None):
    planes = _planes(0)
    make = lambda: optimizer_type([{"name": "grid", "params": planes, "lr": 0.0}],  # noqa: E731
                                  lr=0.0, eps=1e-15, fused=True)
    opt = make()
    for k in range(steps):
        opt.param_groups[0]["lr"] = 1e-2 * (0.9 ** k)
        opt.zero_grad(set_to_none=True)
        _set_grads(planes, k)
        opt.step()
        if reload_at == k:  # a checkpoint written and read back (a resumed run)
            buf = io.BytesIO()
            torch.save(opt.state_dict(), buf)
            buf.seek(0)
            opt = make()
            opt.load_state_dict(torch.load(buf, weights_only=True))
    return planes, opt


@pytest.mark.parametrize("reload_at", [None, 1])
def test_flat_step_equals_torch_per_plane(reload_at):
    got, opt = _run(TrainingAdam, 4, reload_at)
    want, ref = _run(torch.optim.Adam, 4, reload_at)
    assert getattr(opt, "_flat_cache", None), "the flat path did not run"
    for a, b in zip(got, want):
        assert torch.equal(a.detach(), b.detach())
    for a, b in zip(got, want):  # the moments and the counts too, as a checkpoint holds them
        sa, sb = opt.state[a], ref.state[b]
        for name in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(sa[name], sb[name]), name
    assert float(opt.state[got[0]]["step"]) == 4.0


def test_planes_of_their_own_take_torch_path():
    planes = [torch.nn.Parameter(p.detach().clone()) for p in _planes(0)]  # no shared buffer
    opt = TrainingAdam([{"name": "grid", "params": planes, "lr": 1e-2}], eps=1e-15, fused=True)
    ref_planes = [torch.nn.Parameter(p.detach().clone()) for p in planes]
    ref = torch.optim.Adam([{"params": ref_planes, "lr": 1e-2}], eps=1e-15, fused=True)
    for k in range(2):
        for o, ps in ((opt, planes), (ref, ref_planes)):
            o.zero_grad(set_to_none=True)
            _set_grads(ps, k)
        opt.step()
        ref.step()
    assert not getattr(opt, "_flat_cache", None)
    for a, b in zip(planes, ref_planes):
        assert torch.equal(a.detach(), b.detach())
    assert all(p.grad is not None for p in planes)  # gradients handed back untouched


def test_gradient_in_another_layout_is_read_by_index():
    """A gradient laid out otherwise than its plane (not what autograd gives, but allowed) is
    read element by element: after one step each moment is (1 - beta1) g, where torch's fused
    kernel pairs the two arrays' memory instead (measured on torch 2.13)."""
    planes = _planes(0)
    opt = TrainingAdam([{"name": "grid", "params": planes, "lr": 1e-3}], eps=1e-15, fused=True)
    gen = torch.Generator().manual_seed(5)
    for p in planes:
        p.grad = torch.randn(p.shape, generator=gen)  # channel-first, the planes channel-last
    opt.step()
    for p in planes:
        assert not p.grad.is_contiguous(memory_format=torch.channels_last)
        torch.testing.assert_close(opt.state[p]["exp_avg"], 0.1 * p.grad, rtol=1e-6, atol=0)


def test_training_loop_with_gradients_kept_in_one_array():
    """A loop as the trainer runs it (zero_grad, the lookup and the regularisers, backward,
    step), where TrainingAdam's zero_grad gives the planes views of one gradient array: the
    planes, moments and step counts equal torch's fused Adam's bit for bit, and the steps where
    the planes get no gradient (the static stage) leave them and their counts as torch does."""
    from nehad.field.hexplane import PLANE_AXES, TIME_PLANES
    from nehad.field.hexplane_kernel import hexplane_lookup
    from nehad.field.plane_regularisers import plane_regularisers

    def run(optimizer_type):
        planes = _planes(0)
        other = torch.nn.Parameter(torch.ones(3))
        opt = optimizer_type([{"name": "grid", "params": planes, "lr": 1e-2},
                              {"name": "other", "params": [other], "lr": 1e-2}],
                             eps=1e-15, fused=True)
        timed = [k in TIME_PLANES for _ in range(2) for k in range(len(PLANE_AXES))]
        gen = torch.Generator().manual_seed(9)
        for step in range(6):
            opt.zero_grad(set_to_none=True)
            loss = (other * other).sum()
            if step not in (0, 3):  # steps 0 and 3: no plane gradient
                u = torch.rand((50, 4), generator=gen) * 2 - 1
                f = hexplane_lookup(u, planes, PLANE_AXES)
                loss = loss + (f * torch.randn(f.shape, generator=gen)).sum()
                loss = loss + sum(w * r for w, r in zip((0.3, 0.7, 1.9),
                                                        plane_regularisers(planes, timed)))
            loss.backward()
            opt.step()
        return planes, opt

    got, opt = run(TrainingAdam)
    want, ref = run(torch.optim.Adam)
    assert got[0].grad.untyped_storage().data_ptr() == got[1].grad.untyped_storage().data_ptr()
    for a, b in zip(got, want):
        assert torch.equal(a.detach(), b.detach())
        for name in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt.state[a][name], ref.state[b][name]), name
    assert float(opt.state[got[0]]["step"]) == 4.0


def test_gradients_replaced_after_zero_grad_are_used():
    """A caller that drops the planes' gradients after TrainingAdam.zero_grad (a module's
    zero_grad(set_to_none=True)) and runs a backward: its fresh gradients are stepped, as torch
    steps them, not taken for the untouched zeroed array."""
    def run(optimizer_type):
        planes = _planes(0)
        opt = optimizer_type([{"name": "grid", "params": planes, "lr": 1e-2}], eps=1e-15,
                             fused=True)
        for k in range(3):
            opt.zero_grad(set_to_none=True)
            for p in planes:
                p.grad = None
            _set_grads(planes, k)
            opt.step()
        return planes, opt

    got, opt = run(TrainingAdam)
    want, _ = run(torch.optim.Adam)
    for a, b in zip(got, want):
        assert torch.equal(a.detach(), b.detach())
    assert float(opt.state[got[0]]["step"]) == 3.0
