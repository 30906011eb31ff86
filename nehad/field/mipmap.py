"""Scale-aware anisotropic mipmapping of the hex-plane (docs/design.md section 8; paper appendix "Detailed
Methodology of Streaming", the equation for l_hat and beta(rho)).

Read as anti-aliasing of the hex-plane lookups: a Gaussian that spans many plane cells should see
the plane averaged over its footprint, not a point sample of it.

* Pyramids. Every plane gets a mip pyramid by 2x average pooling (`pool2x`). Spatial planes (xy,
  xz, yz) are pooled along both axes; space-time planes (xt, yt, zt) along their spatial axis only:
  a Gaussian has no temporal extent, so halving the time axis would only blur the motion (our
  reading; docs/design.md section 8 does not say). Odd sizes drop the last row/column (floor, as `avg_pool2d`).
  Level k of a scale has 2^k times the level-0 cell; level L_max is the last one whose spatial
  sides are all >= 1 (or `FieldConfig.mipmap_levels` when that is smaller).
* Levels. For a Gaussian with world-axis standard deviations s = (s_x, s_y, s_z) (the square roots
  of the diagonal of R diag(exp(2 log_s)) R^T: its extent along each world axis, so a rotated
  needle gets the right per-axis footprint) and a scale whose cell is cell_a = (aabb_max -
  aabb_min)_a / (res_a - 1) (align_corners=True sampling has res - 1 intervals):
      l_a   = clamp(log2(s_a / cell_a), 0, L_max)          (per axis, docs/design.md section 8)
      L     = max_a l_a   (the dominant axis),  L_bar = mean_a l_a
      rho   = max(l) / min(l)   (guard: min(l) is replaced by 1e-6 when smaller, so rho -> inf
              when an axis is at level 0 while another is not, and beta takes its limit 1/2;
              when all levels are 0, L - L_bar = 0 and beta does not matter)
      beta  = tanh(rho/3 - 1) / (1 + tanh(rho/3 - 1))
      l_hat = clamp(L - beta (L - L_bar), 0, L_max)
  beta is negative for rho < 3 (the formula, taken as docs/design.md writes it, then pushes l_hat above
  L), zero at rho = 3 and tends to 1/2 as rho grows; the final clamp keeps l_hat a valid level.
  The level is computed from the canonical scales and rotation with gradients stopped: the scales
  are not trained to pick a texture level.
* Sampling. Trilinear: bilinear samples (align_corners=True, border clamp, exactly
  `bilinear_gather`) in levels floor(l_hat) and floor(l_hat) + 1, blended linearly with weight
  l_hat - floor(l_hat). All levels of a plane are stacked into one (sum_k H_k W_k, C) table and
  sampled with per-point level offsets and sizes, so the training path and the exported graph are
  the same Gather-based code (only standard ai.onnx ops: Log, Tanh, Floor, Min/Max, Gather, Where,
  ReduceMax/Min/Mean; the pyramids are constant-folded into initializers on export).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

#: rho's guard: min(l) below this is replaced by it (docs/design.md section 8: "guard min = 0").
RHO_EPS = 1e-6
_INV_LN2 = 1.0 / math.log(2.0)


def pool2x(plane: torch.Tensor, pool_height: bool = True) -> torch.Tensor:
    """2x average pooling of a (1, C, H, W) plane along W (and H when `pool_height`); odd sizes
    drop the last column/row. Written with reshape + mean (ReduceMean on export)."""
    _, c, h, w = plane.shape
    w2 = w // 2
    p = plane[..., :, :2 * w2].reshape(1, c, h, w2, 2).mean(-1)
    if pool_height:
        h2 = h // 2
        p = p[..., :2 * h2, :].reshape(1, c, h2, 2, w2).mean(-2)
    return p


def auto_levels(spatial_res: Sequence[int]) -> int:
    """L_max of a scale whose spatial plane sides are `spatial_res`: halvings until a side is 1."""
    return int(math.floor(math.log2(max(1, min(int(r) for r in spatial_res)))))


def build_pyramid(plane: torch.Tensor, levels: int, pool_height: bool) -> list[torch.Tensor]:
    """[P_0 = plane, P_1, ..., P_levels]."""
    out = [plane]
    for _ in range(levels):
        out.append(pool2x(out[-1], pool_height))
    return out


def world_axis_sigma(log_scales: torch.Tensor, quats: torch.Tensor,
                     eps: float = 1e-12) -> torch.Tensor:
    """(N, 3) standard deviations of the Gaussians along the world axes:
    sqrt(diag(R diag(s^2) R^T)) with s = exp(log_scales), R from the (unnormalised) wxyz quats."""
    q = quats / torch.sqrt((quats * quats).sum(-1, keepdim=True) + eps)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)
    s2 = torch.exp(2.0 * log_scales)  # (N, 3)
    var = (r * r * s2[:, None, :]).sum(-1)  # (N, 3): sum_j R_aj^2 s_j^2
    return torch.sqrt(var + eps)


def beta_of_rho(rho: torch.Tensor) -> torch.Tensor:
    """beta(rho) = tanh(rho/3 - 1) / (1 + tanh(rho/3 - 1)) (paper appendix, docs/design.md section 8)."""
    th = torch.tanh(rho * (1.0 / 3.0) - 1.0)
    return th / (1.0 + th)


def mip_level(sigma_cells: torch.Tensor, l_max: int) -> torch.Tensor:
    """l_hat (N,) from per-axis footprints in units of this scale's cell, sigma_cells (N, 3)
    (see the module doc for the formula)."""
    l = (torch.log(sigma_cells) * _INV_LN2).clamp(0.0, float(l_max))
    big = l.max(dim=1).values
    small = l.min(dim=1).values
    mean = l.mean(dim=1)
    rho = big / small.clamp(min=RHO_EPS)
    level = big - beta_of_rho(rho) * (big - mean)
    return level.clamp(0.0, float(l_max))


class PlanePyramid:
    """A plane's mip levels stacked into one (sum_k H_k W_k, C) table for per-point sampling."""

    def __init__(self, levels: list[torch.Tensor]):
        c = levels[0].shape[1]
        self.heights = [int(p.shape[2]) for p in levels]
        self.widths = [int(p.shape[3]) for p in levels]
        offsets, total = [], 0
        for h, w in zip(self.heights, self.widths):
            offsets.append(total)
            total += h * w
        self.offsets = offsets
        self.table = torch.cat([p.reshape(c, -1).transpose(0, 1) for p in levels], 0)

    def sample(self, xy: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
        """Bilinear samples (N, C) at points xy (N, 2) in [-1, 1] (x along W) in integer levels
        `level` (N,) int64, with align_corners=True and border clamping (= `bilinear_gather` of
        that level)."""
        dev, dt = xy.device, xy.dtype
        hs = torch.tensor(self.heights, device=dev, dtype=dt)[level]
        ws = torch.tensor(self.widths, device=dev, dtype=dt)[level]
        off = torch.tensor(self.offsets, device=dev, dtype=torch.int64)[level]
        px = torch.minimum(((xy[:, 0] + 1.0) * (0.5 * (ws - 1.0))).clamp(min=0.0), ws - 1.0)
        py = torch.minimum(((xy[:, 1] + 1.0) * (0.5 * (hs - 1.0))).clamp(min=0.0), hs - 1.0)
        x0 = torch.minimum(px.floor(), (ws - 2.0).clamp(min=0.0))
        y0 = torch.minimum(py.floor(), (hs - 2.0).clamp(min=0.0))
        fx = (px - x0).unsqueeze(1)
        fy = (py - y0).unsqueeze(1)
        wi = ws.to(torch.int64)
        i00 = off + y0.to(torch.int64) * wi + x0.to(torch.int64)
        dx = (ws > 1.0).to(torch.int64)
        dy = torch.where(hs > 1.0, wi, torch.zeros_like(wi))
        t = self.table
        top = t[i00] * (1.0 - fx) + t[i00 + dx] * fx
        bottom = t[i00 + dy] * (1.0 - fx) + t[i00 + dy + dx] * fx
        return top * (1.0 - fy) + bottom * fy

    def sample_trilinear(self, xy: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
        """Trilinear samples (N, C): bilinear in levels floor(level) and floor(level) + 1,
        blended linearly; `level` (N,) float in [0, L_max]."""
        l_max = len(self.heights) - 1
        if l_max == 0:
            return self.sample(xy, torch.zeros_like(level, dtype=torch.int64))
        lo = torch.minimum(level.floor(), torch.full_like(level, float(l_max - 1)))
        w = (level - lo).unsqueeze(1)
        lo_i = lo.to(torch.int64)
        return self.sample(xy, lo_i) * (1.0 - w) + self.sample(xy, lo_i + 1) * w


__all__ = ["PlanePyramid", "RHO_EPS", "auto_levels", "beta_of_rho", "build_pyramid", "mip_level",
           "pool2x", "world_axis_sigma"]
