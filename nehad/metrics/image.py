"""Full-reference image metrics in torch, as 3DGS/4DGS report them (docs/design.md section 9).

All functions take a rendered image and its reference as (H, W, C) or (N, H, W, C) arrays or
tensors with values in [0, 1] (NumPy arrays, torch tensors, or uint8/uint16 images, which are
scaled by 1/255 or 1/65535). They compute in float64 and return one Python float; for a batch the
float is the mean over the images of the per-image value (what an average over test views is).

- ``psnr``: 20 log10(1 / sqrt(MSE)) over all pixels and channels.
- ``ssim``: the 3DGS SSIM: 11x11 Gaussian window (sigma 1.5), zero padding to the input size,
  per channel, mean of the SSIM map (the formula of ``nehad.losses.ssim``, computed here in float64).
- ``ms_ssim``: MS-SSIM exactly as ``pytorch_msssim.ms_ssim(X, Y, data_range=1)`` (version 1.0.0)
  computes it: separable 11-tap Gaussian (sigma 1.5, built in float32), 'valid' filtering, 5 scales
  with weights [0.0448, 0.2856, 0.3001, 0.2363, 0.1333], 2x2 average pooling between scales (with
  padding ``size % 2`` and zero-counting borders), relu of the contrast-structure terms and of the
  last scale's SSIM, product over scales per image and channel, mean over channels. The shorter
  image side must exceed (11 - 1) * 2**4 = 160 pixels (as in pytorch_msssim).
- ``d_ssim``: (1 - MS-SSIM) / 2, the "D-SSIM" column of the DyNeRF/4DGS tables.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
_SSIM_C1 = 0.01 ** 2  # (K1 * data_range)^2, data_range 1
_SSIM_C2 = 0.03 ** 2


def as_image_tensor(x, dtype=torch.float64) -> torch.Tensor:
    """(H, W, C) or (N, H, W, C) array/tensor -> (N, H, W, C) tensor of `dtype` in [0, 1] units.

    Integer images are scaled by their type's maximum (uint8: 255, uint16: 65535); float values are
    taken as they are (no clipping)."""
    if isinstance(x, torch.Tensor):
        t = x.detach().cpu()
        if t.dtype == torch.uint8:
            t = t.to(dtype) / 255.0
        elif not t.is_floating_point():
            raise TypeError(f"unsupported image tensor dtype {t.dtype}; give floats in [0, 1] or uint8")
    else:
        a = np.asarray(x)
        if a.dtype == np.uint8:
            a = a.astype(np.float64) / 255.0
        elif a.dtype == np.uint16:
            a = a.astype(np.float64) / 65535.0
        elif not np.issubdtype(a.dtype, np.floating):
            raise TypeError(f"unsupported image dtype {a.dtype}; give floats in [0, 1], uint8 or uint16")
        a = np.ascontiguousarray(a)
        if not a.flags.writeable:  # a read-only view (torch warns on those): a copy
            a = a.copy()
        t = torch.from_numpy(a)
    t = t.to(dtype)
    if t.dim() == 3:
        t = t[None]
    if t.dim() != 4:
        raise ValueError(f"expected an (H, W, C) or (N, H, W, C) image, got shape {tuple(t.shape)}")
    return t


def _pair(img, ref, dtype=torch.float64):
    a, b = as_image_tensor(img, dtype), as_image_tensor(ref, dtype)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    return a, b


def psnr_of_mse(mse):
    """PSNR in dB of the mean squared error of [0, 1] images: 20 log10(1 / sqrt(MSE)) =
    -10 log10(MSE); inf for a zero error. The project's one PSNR formula (a float, or an array
    elementwise); every other PSNR computes an MSE and calls this."""
    with np.errstate(divide="ignore"):
        out = -10.0 * np.log10(np.asarray(mse, np.float64))
    return float(out) if np.ndim(out) == 0 else out


def psnr(img, ref) -> float:
    """PSNR in dB of [0, 1] images (`psnr_of_mse`); mean over a batch; inf if identical."""
    a, b = _pair(img, ref)
    mse = ((a - b) ** 2).flatten(1).mean(1)
    return float(np.mean(psnr_of_mse(mse.numpy())))


def ssim(img, ref) -> float:
    """3DGS SSIM (11x11 Gaussian window, sigma 1.5, zero padding, 'same' size), mean over a batch.

    Same formula as ``nehad.losses.ssim`` (the 3DGS training SSIM), computed in float64 with the
    window applied as two 1-D passes (the 2-D window is their outer product) over the five maps
    at once: much faster on the CPU than a float64 2-D depthwise convolution. Agrees with
    ``nehad.losses.ssim`` to ~1e-9 in float64 (that one rounds its window to float32)."""
    a, b = _pair(img, ref)
    x, y = a.permute(0, 3, 1, 2).contiguous(), b.permute(0, 3, 1, 2).contiguous()
    c = x.shape[1]
    g = torch.arange(11, dtype=x.dtype) - 5
    g = torch.exp(-g * g / (2 * 1.5 ** 2))
    g = g / g.sum()
    stack = F.pad(torch.cat([x, y, x * x, y * y, x * y], 1), (5, 5, 5, 5))
    blur = _blur_valid(stack, g)
    mu_x, mu_y, exx, eyy, exy = blur.split(c, 1)
    sxx, syy, sxy = exx - mu_x * mu_x, eyy - mu_y * mu_y, exy - mu_x * mu_y
    c1, c2 = _SSIM_C1, _SSIM_C2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    return float((num / den).mean())


def _gauss_1d(size: int, sigma: float) -> torch.Tensor:
    # Built as pytorch_msssim._fspecial_gauss_1d does (float32), then cast by the caller.
    coords = torch.arange(size, dtype=torch.float32)
    coords -= size // 2
    g = torch.exp(-(coords ** 2) / (2 * sigma ** 2))
    g /= g.sum()
    return g


def _blur_valid(x: torch.Tensor, win: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' filtering of (N, C, H, W) by the 1-D window `win`, per channel, H first
    then W (the order of pytorch_msssim). Written as in-place sums of shifted slices: the same
    arithmetic as a depthwise convolution, which torch runs slowly in float64 on the CPU (0.2 s
    instead of 0.7 s for 15 maps of 800x800; a 2-D 11x11 float64 depthwise conv takes 7 s)."""
    k = win.numel()
    h, w = x.shape[-2] - k + 1, x.shape[-1] - k + 1
    wl = win.tolist()
    out = x[..., 0:h, :] * wl[0]
    for i in range(1, k):
        out.add_(x[..., i:i + h, :], alpha=wl[i])
    res = out[..., 0:w] * wl[0]
    for i in range(1, k):
        res.add_(out[..., i:i + w], alpha=wl[i])
    return res


def _ssim_cs(x, y, win, data_range, K):
    c1 = (K[0] * data_range) ** 2
    c2 = (K[1] * data_range) ** 2
    c = x.shape[1]
    mu1, mu2, exx, eyy, exy = _blur_valid(torch.cat([x, y, x * x, y * y, x * y], 1), win).split(c, 1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1 = exx - mu1_sq
    s2 = eyy - mu2_sq
    s12 = exy - mu1_mu2
    cs_map = (2 * s12 + c2) / (s1 + s2 + c2)
    ssim_map = ((2 * mu1_mu2 + c1) / (mu1_sq + mu2_sq + c1)) * cs_map
    return ssim_map.flatten(2).mean(-1), cs_map.flatten(2).mean(-1)  # (N, C) each


def ms_ssim_per_image(img, ref, data_range: float = 1.0, win_size: int = 11, win_sigma: float = 1.5,
                      weights=MS_SSIM_WEIGHTS, K=(0.01, 0.03)) -> torch.Tensor:
    """MS-SSIM of each image of a batch, as pytorch_msssim.ms_ssim(..., size_average=False)."""
    x, y = _pair(img, ref)
    x, y = x.permute(0, 3, 1, 2).contiguous(), y.permute(0, 3, 1, 2).contiguous()
    if win_size % 2 != 1:
        raise ValueError("window size must be odd")
    levels = len(weights)
    min_side = (win_size - 1) * 2 ** (levels - 1)
    if min(x.shape[-2:]) <= min_side:
        raise ValueError(f"MS-SSIM needs both image sides larger than {min_side} pixels "
                         f"({levels - 1} downsamplings of an {win_size}-tap window); got "
                         f"{tuple(x.shape[-2:])}")
    win = _gauss_1d(win_size, win_sigma).to(x.dtype)
    w = torch.tensor(weights, dtype=x.dtype)
    mcs = []
    for i in range(levels):
        ssim_pc, cs = _ssim_cs(x, y, win, data_range, K)
        if i < levels - 1:
            mcs.append(torch.relu(cs))
            pad = [s % 2 for s in x.shape[2:]]
            x = F.avg_pool2d(x, kernel_size=2, padding=pad)
            y = F.avg_pool2d(y, kernel_size=2, padding=pad)
    ssim_pc = torch.relu(ssim_pc)
    stack = torch.stack(mcs + [ssim_pc], dim=0)  # (levels, N, C)
    return torch.prod(stack ** w.view(-1, 1, 1), dim=0).mean(1)


def ms_ssim(img, ref, data_range: float = 1.0, **kw) -> float:
    """MS-SSIM (pytorch_msssim semantics, data_range 1), mean over a batch."""
    return float(ms_ssim_per_image(img, ref, data_range=data_range, **kw).mean())


def d_ssim(img, ref) -> float:
    """D-SSIM = (1 - MS-SSIM) / 2 (DyNeRF / 4DGS tables)."""
    return (1.0 - ms_ssim(img, ref)) / 2.0
