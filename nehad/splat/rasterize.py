"""Differentiable rasterization for training: a `torch.autograd.Function` around the shared Numba
kernels of `nehad.runtime.raster` (docs/design.md section 6), so what trains is what renders.

The backward pass gives gradients for the 2D means, conics, colours and opacities; the projection's
own backward (`project_gaussians_numba`) carries them to the 3D parameters. Densification reads the
view-space mean gradient from `means2d.grad` (see `viewspace_grad_norm`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nehad.runtime.raster import rasterize as _rasterize_np
from nehad.runtime.raster import rasterize_backward as _rasterize_backward_np

from .projection import ProjectedTorch, _np32, project_gaussians_numba


class RasterizeGaussians(torch.autograd.Function):
    """(means2d, conics, colors, opacities, depths, radii) -> (rgb (H,W,3), alpha (H,W), depth)."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, width, height, background):
        out = _rasterize_np(_np32(means2d), _np32(conics), _np32(colors), _np32(opacities),
                            _np32(depths), radii.detach().cpu().numpy().astype(np.int32),
                            width, height, background)
        ctx.raster_out = out
        ctx.n = means2d.shape[0]
        dev, dt = means2d.device, means2d.dtype
        rgb = torch.from_numpy(out.rgb).to(dev, dt)
        alpha = torch.from_numpy(out.alpha).to(dev, dt)
        depth = torch.from_numpy(out.depth).to(dev, dt)
        ctx.mark_non_differentiable(depth)
        return rgb, alpha, depth

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha, grad_depth):
        out = ctx.raster_out
        h, w = out.final_t.shape
        g_rgb = np.zeros((h, w, 3), np.float32) if grad_rgb is None else _np32(grad_rgb)
        g_alpha = np.zeros((h, w), np.float32) if grad_alpha is None else _np32(grad_alpha)
        g = _rasterize_backward_np(out, g_rgb, g_alpha)
        dev = grad_rgb.device if grad_rgb is not None else "cpu"
        dt = grad_rgb.dtype if grad_rgb is not None else torch.float32
        to = lambda a: torch.from_numpy(a).to(dev, dt)
        return (to(g.means2d), to(g.conics), to(g.colors), to(g.opacities),
                None, None, None, None, None)


def rasterize_torch(proj: ProjectedTorch, width: int, height: int, background=(0.0, 0.0, 0.0)):
    """Rasterize projected Gaussians; returns rgb (H, W, 3), alpha (H, W), depth (H, W)."""
    bg = tuple(float(v) for v in background)
    return RasterizeGaussians.apply(proj.means2d, proj.conics, proj.colors, proj.opacities,
                                    proj.depths, proj.radii, int(width), int(height), bg)


@dataclass
class RenderResult:
    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    means2d: torch.Tensor  # keeps .grad after backward (view-space gradient for densification)
    radii: torch.Tensor


def render_torch(means, scales, quats, opacities, sh, camera, background=(0.0, 0.0, 0.0),
                 sh_degree: int | None = None) -> RenderResult:
    """Project and rasterize activated Gaussian tensors through a `Camera` (differentiable)."""
    proj = project_gaussians_numba(means, scales, quats, opacities, sh, camera, sh_degree)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    rgb, alpha, depth = rasterize_torch(proj, camera.width, camera.height, background)
    return RenderResult(rgb, alpha, depth, proj.means2d, proj.radii)


def viewspace_grad_norm(means2d_grad: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """|dL/d mean2d| in normalised device coordinates, the statistic 3DGS densifies on
    (pixel = ((ndc + 1) W - 1) / 2, so dL/d ndc = dL/d pixel * W / 2)."""
    scale = torch.tensor([width / 2.0, height / 2.0], dtype=means2d_grad.dtype,
                         device=means2d_grad.device)
    return (means2d_grad * scale).norm(dim=-1)
