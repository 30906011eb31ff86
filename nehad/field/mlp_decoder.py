"""4DGS baseline decoder (`decoder: mlp`, the first row of the paper's ablation; docs/design.md section 4 last
paragraph; paper Sec. "Dynamic Gaussian Splatting": dmu = D_mu(f), ds = D_s(f), dr = D_r(f)).

Per-attribute heads ReLU-Linear(W, W)-ReLU-Linear(W, k) on the trunk output h, as 4DGS's
`pos_deform`, `scales_deform`, `rotations_deform` (+ `opacity_deform`, `shs_deform`). The last
layer of every head is zero-initialised so the fine stage starts at the identity deformation
(4DGS itself does not zero them; we do, to match the HNN path's identity start).
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import nn


def _head(width: int, k: int) -> nn.Sequential:
    last = nn.Linear(width, k)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), last)


class MLPHeads(nn.Module):
    """h (N, W) -> dict(dmu (N, 3), ds (N, 3), dr (N, 4)[, d_opacity (N, 1), d_sh (N, K, 3)])."""

    def __init__(self, width: int = 64, deform_appearance: bool = False, sh_coeffs: int = 16):
        super().__init__()
        self.pos = _head(width, 3)
        self.scale = _head(width, 3)
        self.rot = _head(width, 4)
        self.sh_coeffs = sh_coeffs
        if deform_appearance:
            self.opacity = _head(width, 1)
            self.sh = _head(width, 3 * sh_coeffs)
        else:
            self.opacity = self.sh = None

    def forward(self, h: torch.Tensor) -> dict[str, Optional[torch.Tensor]]:
        out = {"dmu": self.pos(h), "ds": self.scale(h), "dr": self.rot(h),
               "d_opacity": None, "d_sh": None}
        if self.opacity is not None:
            out["d_opacity"] = self.opacity(h)
            out["d_sh"] = self.sh(h).reshape(h.shape[0], self.sh_coeffs, 3)
        return out


__all__ = ["MLPHeads"]
