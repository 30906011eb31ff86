"""The fused Numba photometric loss (nehad.fused_loss) against torch autograd in float64."""

import numpy as np
import pytest
import torch

from nehad.config import build_config
from nehad.configtools import ConfigError
from nehad.fused_loss import photometric_loss_and_grad
from nehad.losses import photometric_loss


def _pair(h, w, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(h, w, 3, generator=g, dtype=dtype)
    img = (ref + 0.15 * torch.randn(h, w, 3, generator=g, dtype=dtype)).clamp(0, 1)
    return img, ref


@pytest.mark.parametrize("h,w,weight", [(17, 23, 0.2), (40, 31, 0.2), (12, 12, 1.0), (9, 30, 0.0)])
def test_loss_and_gradient_match_autograd_float64(h, w, weight):
    img, ref = _pair(h, w, seed=h * w)
    img.requires_grad_(True)
    want = photometric_loss(img, ref, weight)  # the torch reference, float64
    want.backward()
    loss, grad = photometric_loss_and_grad(img.detach().float().numpy(), ref.float().numpy(),
                                           weight)
    want = want.item()
    assert abs(loss - want) <= 1e-6 * abs(want)
    ref_grad = img.grad.numpy()
    assert np.abs(grad - ref_grad).max() <= 1e-5 * np.abs(ref_grad).max()


def test_gradient_matches_finite_differences():
    img, ref = _pair(13, 11, seed=5)
    x, y = img.float().numpy(), ref.float().numpy()
    _, grad = photometric_loss_and_grad(x, y, 0.2)
    rng = np.random.default_rng(0)
    for _ in range(6):
        i, j, c = rng.integers(13), rng.integers(11), rng.integers(3)
        if abs(x[i, j, c] - y[i, j, c]) < 1e-2:  # keep |x - y| differentiable over the step
            continue
        up, down = x.copy(), x.copy()
        up[i, j, c] += 1e-3
        down[i, j, c] -= 1e-3
        xd, yd = up.astype(np.float64), y.astype(np.float64)
        fd = (float(photometric_loss(torch.from_numpy(xd), torch.from_numpy(yd), 0.2))
              - float(photometric_loss(torch.from_numpy(down.astype(np.float64)),
                                       torch.from_numpy(yd), 0.2))) / 2e-3
        assert abs(grad[i, j, c] - fd) <= 1e-3 * abs(fd) + 1e-8


def test_photometric_loss_dispatch():
    img, ref = _pair(24, 20, seed=3, dtype=torch.float32)
    a = img.clone().requires_grad_(True)
    b = img.clone().requires_grad_(True)
    la = photometric_loss(a, ref, 0.2, kernel="numba")
    lb = photometric_loss(b, ref, 0.2, kernel="torch")
    (3.0 * la).backward()
    (3.0 * lb).backward()
    assert la.grad_fn is not None and type(la.grad_fn).__name__ != type(lb.grad_fn).__name__
    assert abs(float(la) - float(lb)) <= 1e-6
    assert torch.allclose(a.grad, b.grad, rtol=1e-4, atol=1e-9)
    # float64 or batched images take the autograd path
    c = img.double().requires_grad_(True)
    assert photometric_loss(c, ref.double(), 0.2, kernel="numba").grad_fn is not None


def test_loss_kernel_is_validated():
    assert build_config("test", None, []).loss.kernel == "numba"
    with pytest.raises(ConfigError, match="loss.kernel"):
        build_config("test", None, ["loss.kernel=cuda"])
