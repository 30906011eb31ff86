"""Image losses and similarity in torch (SPEC sections 5 and 9): L1 and SSIM with the 3DGS
11-tap Gaussian window (sigma 1.5)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

_SSIM_C1 = 0.01 ** 2
_SSIM_C2 = 0.03 ** 2


def _gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device="cpu"):
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim(img: torch.Tensor, ref: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) or (B, H, W, C) images in [0, 1] (3DGS: zero padding,
    'same' size, per-channel 11x11 Gaussian window)."""
    if img.dim() == 3:
        img, ref = img[None], ref[None]
    x = img.permute(0, 3, 1, 2)
    y = ref.permute(0, 3, 1, 2)
    c = x.shape[1]
    w = _gaussian_window(window, dtype=x.dtype, device=x.device).expand(c, 1, window, window)
    pad = window // 2
    blur = lambda t: F.conv2d(t, w, padding=pad, groups=c)
    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x * mu_x
    syy = blur(y * y) - mu_y * mu_y
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + _SSIM_C1) * (2 * sxy + _SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + _SSIM_C1) * (sxx + syy + _SSIM_C2)
    return (num / den).mean()


def photometric_loss(img: torch.Tensor, ref: torch.Tensor, ssim_weight: float = 0.2):
    """(1 - w) L1 + w D-SSIM with D-SSIM = 1 - SSIM, the 3DGS/4DGS image loss (SPEC section 5)."""
    l1 = (img - ref).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(img, ref))


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """20 log10(1 / sqrt(MSE)) on [0, 1] images (SPEC section 9)."""
    mse = torch.mean((img.detach().clamp(0, 1) - ref) ** 2).item()
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
