"""The fused rotation step (nehad.field.rigidity_kernel) against the torch reference
(nehad.field.rigidity: clamp_rotation_delta, quat_multiply, safe_normalize) in float64: values
and the gradients of every input, and inside DeformationField."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.field.rigidity import clamp_rotation_delta, quat_multiply, safe_normalize  # noqa: E402
from nehad.field.rigidity_kernel import clamped_rotation  # noqa: E402


def _reference(quats, q, phi_max, eps):
    rd = clamp_rotation_delta(q, phi_max, eps)
    return safe_normalize(quat_multiply(quats, rd.dr), eps), rd.phi, rd.phi_clamped


def _inputs(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=1)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    q[:8, 0] = -q[:8, 0].abs()  # angles past pi
    q[8:12, 1:] = 1e-9 * q[8:12, 1:]  # nearly no rotation
    q[12:16] *= 30.0  # not unit
    return quats, q


@pytest.mark.parametrize("phi_max", [math.pi, 0.5])
def test_values_and_gradients_match_the_torch_functions(phi_max):
    quats, q = _inputs()
    g = torch.Generator().manual_seed(9)
    ups = [torch.randn(64, k, generator=g, dtype=torch.float64) for k in (4, 1, 1)]
    results = []
    for fn in (_reference, clamped_rotation):
        a = quats.clone().requires_grad_(True)
        b = q.clone().requires_grad_(True)
        outs = fn(a, b, phi_max, 1e-12)
        loss = sum((o * u).sum() for o, u in zip(outs, ups))
        results.append(([o.detach() for o in outs], torch.autograd.grad(loss, (a, b))))
    (ref_out, ref_grads), (out, grads) = results
    for x, y in zip(out, ref_out):
        assert (x - y).abs().max() <= 1e-12 * max(1.0, float(y.abs().max()))
    for x, y in zip(grads, ref_grads):
        assert float(y.abs().max()) > 0
        assert (x - y).abs().max() <= 1e-9 * float(y.abs().max())


def test_unused_angle_outputs_and_float32():
    """Only r' used (phi, phi' get no gradient): the same gradients as the reference; float32
    within float32 rounding of float64."""
    quats, q = _inputs(seed=1)
    up = torch.randn(64, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    grads = []
    for fn, dtype in ((_reference, torch.float64), (clamped_rotation, torch.float64),
                      (clamped_rotation, torch.float32)):
        a = quats.to(dtype).requires_grad_(True)
        b = q.to(dtype).requires_grad_(True)
        out = fn(a, b, math.pi, 1e-12)[0]
        grads.append([t.double() for t in torch.autograd.grad((out * up.to(dtype)).sum(), (a, b))])
    for x, y in zip(grads[1], grads[0]):
        assert (x - y).abs().max() <= 1e-9 * float(y.abs().max())
    for x, y in zip(grads[2], grads[0]):
        assert (x - y).abs().max() <= 1e-4 * float(y.abs().max())


def test_the_field_uses_it_and_agrees_with_the_torch_path():
    """DeformationField with rotation_kernel "numba" and "torch": the same quaternions and the
    same gradients (float64)."""
    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField

    torch.manual_seed(3)
    cfgs = [FieldConfig(resolution=(6, 6, 6, 4), width=8, hnn_hidden=6, hnn_depth=1,
                        rotation_kernel=k) for k in ("numba", "torch")]
    fields = [DeformationField(c, np.array([[-1.0] * 3, [1.0] * 3]), 2.0).double() for c in cfgs]
    fields[1].load_state_dict(fields[0].state_dict())
    with torch.no_grad():
        for p in fields[0].adapters.parameters():
            p.normal_(0.0, 0.3)
        fields[1].load_state_dict(fields[0].state_dict())
    n = 20
    means = torch.rand(n, 3, dtype=torch.float64) * 2 - 1
    scales = torch.rand(n, 3, dtype=torch.float64) - 3.0
    quats = torch.nn.functional.normalize(torch.randn(n, 4, dtype=torch.float64), dim=1)
    up = torch.randn(n, 4, dtype=torch.float64)
    results = []
    for f in fields:
        params = list(f.parameters())
        out = f(means, scales, quats, 0.3)
        loss = (out.quats * up).sum()
        results.append((out.quats.detach(), torch.autograd.grad(loss, params, allow_unused=True)))
    assert (results[0][0] - results[1][0]).abs().max() <= 1e-12
    moved = 0
    for x, y in zip(results[0][1], results[1][1]):
        assert (x is None) == (y is None)
        if x is not None:
            assert (x - y).abs().max() <= 1e-9 * max(float(y.abs().max()), 1e-30)
            moved += float(y.abs().max()) > 0
    assert moved >= 3
