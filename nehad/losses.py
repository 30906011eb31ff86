"""Image losses and similarity in torch (docs/design.md sections 5 and 9): L1 and SSIM with the 3DGS
11-tap Gaussian window (sigma 1.5)."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from nehad.blur import gaussian_blur, gaussian_taps

_SSIM_C1 = 0.01 ** 2
_SSIM_C2 = 0.03 ** 2


class _GaussianBlur(torch.autograd.Function):
    """Blur of a (M, H, W) stack; self-adjoint, so backward blurs the gradient."""

    @staticmethod
    def forward(ctx, stack, taps):
        ctx.taps = taps
        out = gaussian_blur(stack.detach().cpu().numpy(), taps)
        return torch.from_numpy(out).to(stack.device, stack.dtype)

    @staticmethod
    def backward(ctx, grad):
        out = gaussian_blur(grad.detach().cpu().numpy(), ctx.taps)
        return torch.from_numpy(out).to(grad.device, grad.dtype), None


def _blur(stack: torch.Tensor, window: int, sigma: float = 1.5) -> torch.Tensor:
    """Gaussian blur (`window` taps, sigma 1.5 for SSIM, zero padding) of a (B, C, H, W)
    tensor."""
    b, c, h, w = stack.shape
    taps = gaussian_taps(window, sigma)
    if stack.device.type != "cpu" or stack.dtype != torch.float32:
        import torch.nn.functional as F

        g = torch.as_tensor(taps, dtype=stack.dtype, device=stack.device)
        pad = window // 2
        wy = g.reshape(1, 1, window, 1).expand(c, 1, window, 1)
        wx = g.reshape(1, 1, 1, window).expand(c, 1, 1, window)
        return F.conv2d(F.conv2d(stack, wy, padding=(pad, 0), groups=c), wx,
                        padding=(0, pad), groups=c)
    return _GaussianBlur.apply(stack.reshape(b * c, h, w), taps).reshape(b, c, h, w)


def ssim(img: torch.Tensor, ref: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) or (B, H, W, C) images in [0, 1] (3DGS: zero padding,
    'same' size, per-channel 11x11 Gaussian window)."""
    if img.dim() == 3:
        img, ref = img[None], ref[None]
    x = img.permute(0, 3, 1, 2).contiguous()
    y = ref.permute(0, 3, 1, 2).contiguous()
    c = x.shape[1]
    # the five local moments go through one separable blur (22 taps, not 121)
    blurred = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), window)
    mu_x, mu_y, exx, eyy, exy = blurred.split(c, 1)
    sxx = exx - mu_x * mu_x
    syy = eyy - mu_y * mu_y
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _SSIM_C1) * (2 * sxy + _SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + _SSIM_C1) * (sxx + syy + _SSIM_C2)
    return (num / den).mean()


def annealed_blur_px(blur: float, until: float, progress: float, width: int) -> float:
    """Sigma in pixels of the blur that `view_loss` puts on both images (docs/training.md,
    "Blurred early steps"): `blur` x the image width at the deforming stage's first step,
    falling linearly to 0 when `progress` (the share of the stage done) reaches `until`."""
    if blur <= 0 or until <= 0 or progress >= until:
        return 0.0
    return blur * width * (1.0 - progress / until)


def blurred(img: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """An (H, W, C) image blurred by a Gaussian of `sigma_px` pixels (taps out to 3 sigma, zero
    padding), differentiable (`_blur`, the SSIM window's blur with wider taps)."""
    radius = max(1, int(np.ceil(3.0 * sigma_px)))
    stack = img.permute(2, 0, 1)[None].contiguous()
    return _blur(stack, 2 * radius + 1, sigma_px)[0].permute(1, 2, 0).contiguous()


def view_loss(img: torch.Tensor, ref: torch.Tensor, loss_cfg, progress: Optional[float]):
    """A training view's image loss: `photometric_loss` of the render against its target, both
    first blurred by `annealed_blur_px` while the deforming stage is young (`progress`, its
    share done; None in the static stage, which is never blurred)."""
    sigma = 0.0 if progress is None else annealed_blur_px(
        loss_cfg.blur, loss_cfg.blur_until, progress, img.shape[1])
    if sigma >= 0.3:  # under a third of a pixel the 3-tap kernel is nearly the identity
        img, ref = blurred(img, sigma), blurred(ref, sigma)
    return photometric_loss(img, ref, loss_cfg.ssim_weight, loss_cfg.kernel)


def photometric_loss(img: torch.Tensor, ref: torch.Tensor, ssim_weight: float = 0.2,
                     kernel: str = "torch"):
    """(1 - w) L1 + w D-SSIM with D-SSIM = 1 - SSIM, the 3DGS/4DGS image loss (docs/design.md section 5).
    `kernel="numba"` computes the same loss and its gradient in the fused passes of
    nehad.fused_loss when `img` is one (H, W, C) float32 CPU image (else this autograd version)."""
    if (kernel == "numba" and ssim_weight > 0 and img.dim() == 3 and img.device.type == "cpu"
            and img.dtype == torch.float32 and ref.dtype == torch.float32
            and not ref.requires_grad):
        from nehad.fused_loss import fused_photometric_loss

        return fused_photometric_loss(img, ref, ssim_weight)
    l1 = (img - ref).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(img, ref))


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """PSNR of a render (clamped to [0, 1]) against its target during training
    (`nehad.metrics.image.psnr_of_mse`)."""
    from nehad.metrics.image import psnr_of_mse

    return psnr_of_mse(torch.mean((img.detach().clamp(0, 1) - ref) ** 2).item())
