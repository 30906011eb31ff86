"""Static 3DGS fit (no deformation): the smallest training loop that proves the rasterizer's
backward pass trains (issue: foundation). The NeHaD trainer builds on the same pieces."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from nehad.gaussians import GaussianParameters
from nehad.losses import photometric_loss, psnr
from nehad.splat.rasterize import render_torch


@dataclass
class StaticFitConfig:
    iterations: int = 1500  # optimisation steps, one random training view each
    sh_degree: int = 1  # SH degree of the fitted Gaussians
    lr_means: float = 1.6e-3  # times the scene extent; higher than 3DGS for short fits
    lr_means_final: float = 1.6e-5  # exponential decay target, times the scene extent
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w D-SSIM
    time_limit_s: float | None = None  # stop early after this many seconds
    seed: int = 0


def fit_static(params: GaussianParameters, cameras, images, cfg: StaticFitConfig,
               background=(1.0, 1.0, 1.0), extent: float = 1.0, progress=None) -> dict:
    """Fit `params` to posed images (list of Camera, list of (H, W, 3) float arrays)."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    targets = [torch.as_tensor(np.asarray(im, np.float32)) for im in images]
    groups = [
        {"params": [params.means], "lr": cfg.lr_means * extent},
        {"params": [params.sh_dc], "lr": cfg.lr_sh_dc},
        {"params": [params.sh_rest], "lr": cfg.lr_sh_rest},
        {"params": [params.opacity_logits], "lr": cfg.lr_opacity},
        {"params": [params.log_scales], "lr": cfg.lr_scales},
        {"params": [params.quats], "lr": cfg.lr_quats},
    ]
    opt = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    decay = (cfg.lr_means_final / cfg.lr_means) ** (1.0 / max(cfg.iterations, 1))
    start = time.perf_counter()
    losses = []
    it = 0
    for it in range(cfg.iterations):
        k = int(rng.integers(len(cameras)))
        res = render_torch(*params.activated(), cameras[k], background=background)
        loss = photometric_loss(res.rgb, targets[k], cfg.ssim_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        groups[0]["lr"] = opt.param_groups[0]["lr"] = opt.param_groups[0]["lr"] * decay
        losses.append(loss.item())
        if progress is not None:
            progress(it, loss.item())
        if cfg.time_limit_s is not None and time.perf_counter() - start > cfg.time_limit_s:
            break
    return {"iterations": it + 1, "seconds": time.perf_counter() - start, "losses": losses}


def evaluate_psnr(params: GaussianParameters, cameras, images, background=(1.0, 1.0, 1.0)):
    """Mean PSNR over views."""
    vals = []
    with torch.no_grad():
        for cam, im in zip(cameras, images):
            res = render_torch(*params.activated(), cam, background=background)
            vals.append(psnr(res.rgb, torch.as_tensor(np.asarray(im, np.float32))))
    return float(np.mean(vals))
