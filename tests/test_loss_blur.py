"""The blur of the deforming stage's first steps (`loss.blur`, nehad.losses.view_loss) against a
float64 convolution, its gradient, and its schedule."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nehad.config import build_config
from nehad.configtools import ConfigError
from nehad.losses import annealed_blur_px, blurred, photometric_loss, view_loss


def _conv64(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """The same blur written independently: a float64 separable conv2d, zero padding."""
    r = int(np.ceil(3 * sigma))
    x = np.arange(-r, r + 1)
    g = np.exp(-x * x / (2 * sigma * sigma))
    g = torch.tensor(g / g.sum())
    s = img.permute(2, 0, 1)[:, None]
    s = F.conv2d(s, g.reshape(1, 1, -1, 1), padding=(r, 0))
    return F.conv2d(s, g.reshape(1, 1, 1, -1), padding=(0, r))[:, 0].permute(1, 2, 0)


@pytest.mark.parametrize("sigma", [0.7, 2.3, 5.0])
def test_blur_and_its_gradient_match_a_float64_convolution(sigma):
    g = torch.Generator().manual_seed(int(sigma * 10))
    img = torch.rand(21, 34, 3, generator=g)
    weights = torch.rand(21, 34, 3, generator=g)
    x = img.clone().requires_grad_(True)
    out = blurred(x, sigma)
    (out * weights).sum().backward()
    x64 = img.double().requires_grad_(True)
    want = _conv64(x64, sigma)
    (want * weights.double()).sum().backward()
    assert (out.double() - want).abs().max().item() < 1e-6
    assert (x.grad.double() - x64.grad).abs().max().item() < 1e-6
    # a blur that did nothing, or went the wrong way, would be far off the reference
    assert (img.double() - want).abs().max().item() > 0.1


def test_schedule_falls_linearly_to_zero():
    assert annealed_blur_px(0.04, 0.5, 0.0, 100) == pytest.approx(4.0)
    assert annealed_blur_px(0.04, 0.5, 0.25, 200) == pytest.approx(4.0)
    assert annealed_blur_px(0.04, 0.5, 0.5, 100) == 0.0
    assert annealed_blur_px(0.0, 0.5, 0.0, 100) == 0.0


def _bar(y, rows=32, cols=32):
    """A thin horizontal bar (a Gaussian profile of 0.6 px) centred on row y, as an image."""
    profile = torch.exp(-(torch.arange(rows, dtype=torch.float32) - y) ** 2 / (2 * 0.6 ** 2))
    img = torch.zeros(rows, cols, 3)
    return img + profile[:, None, None] * (torch.arange(cols) >= 4)[None, :, None]


def test_view_loss_blurs_only_the_young_deforming_stage():
    ref = _bar(torch.tensor(10.5))
    cfg = build_config("cpu", None, ["loss.blur=0.1", "loss.blur_until=0.5"])
    y = torch.tensor(16.0, requires_grad=True)
    img = _bar(y)
    plain = photometric_loss(img, ref, cfg.loss.ssim_weight, cfg.loss.kernel)
    for progress in (None, 0.5, 0.9):  # the static stage, and the blur's end
        assert view_loss(img, ref, cfg.loss, progress).item() == pytest.approx(plain.item())
    # the render's bar 5.5 px from the target's: sharp, only the D-SSIM window's tail sees the
    # other bar; blurred (3.2 px at this width), the loss pulls the bar towards it
    (pull_plain,) = torch.autograd.grad(plain, y, retain_graph=True)
    (pull,) = torch.autograd.grad(view_loss(img, ref, cfg.loss, 0.0), y)
    assert pull.item() > 0  # a smaller y (towards 10.5) lowers the loss
    assert pull.item() > 3 * abs(pull_plain.item())  # measured 4.8x


def test_blur_settings_are_checked():
    with pytest.raises(ConfigError, match="loss.blur"):
        build_config("cpu", None, ["loss.blur=-0.1"])
    with pytest.raises(ConfigError, match="loss.blur_until"):
        build_config("cpu", None, ["loss.blur_until=1.5"])
