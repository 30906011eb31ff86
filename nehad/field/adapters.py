"""Attribute adapters (paper Sec. "Neural Hamiltonian Deformation Fields": dmu = A_mu v,
ds = A_s v, dr = A_r v; docs/design.md section 4.5) and the Verlet force F = A_mu' v_c (docs/design.md section 4.5-4.6)."""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import nn


class AdapterOutput(NamedTuple):
    dmu: torch.Tensor  # (N, 3) position offset ("velocity" of the Verlet step)
    ds: torch.Tensor  # (N, 3) log-scale offset
    q: torch.Tensor  # (N, 4) quaternion delta (1, 0, 0, 0) + A_r v, not normalised
    d_opacity: Optional[torch.Tensor] = None  # (N, 1) when deforming appearance
    d_sh: Optional[torch.Tensor] = None  # (N, K, 3) when deforming appearance


def _zero_linear(i: int, o: int) -> nn.Linear:
    lin = nn.Linear(i, o)
    nn.init.zeros_(lin.weight)
    nn.init.zeros_(lin.bias)
    return lin


class Adapters(nn.Module):
    """Linear, zero-initialised adapters, so a fresh field is the identity deformation.

    `mu`: Linear(W, 3), `scale`: Linear(W, 3), `rot`: Linear(W, 4) (+ `opacity`: Linear(W, 1),
    `sh`: Linear(W, 3K) when `deform_appearance`)."""

    def __init__(self, width: int = 64, deform_appearance: bool = False, sh_coeffs: int = 16):
        super().__init__()
        self.mu = _zero_linear(width, 3)
        self.scale = _zero_linear(width, 3)
        self.rot = _zero_linear(width, 4)
        self.sh_coeffs = sh_coeffs
        if deform_appearance:
            self.opacity = _zero_linear(width, 1)
            self.sh = _zero_linear(width, 3 * sh_coeffs)
        else:
            self.opacity = self.sh = None
        self.register_buffer("identity_quat", torch.tensor([1.0, 0.0, 0.0, 0.0]),
                             persistent=False)

    def _layers(self) -> list[nn.Linear]:
        """mu, scale, rot (+ opacity, sh): the order of `stacked` and `split`."""
        layers = [self.mu, self.scale, self.rot]
        if self.opacity is not None:
            layers += [self.opacity, self.sh]
        return layers

    def stacked(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(weight (K, W), bias (K,)) of the adapters stacked (`_layers`)."""
        layers = self._layers()
        return torch.cat([lin.weight for lin in layers]), torch.cat([lin.bias for lin in layers])

    def forward(self, v: torch.Tensor) -> AdapterOutput:
        # the adapters as one product of v with their stacked weights, then split: one matrix
        # product (and one for each gradient) instead of one per adapter (10k Gaussians: 1.5
        # -> 1.0 ms forward and backward with the force, docs/performance.md)
        return self.split(F.linear(v, *self.stacked()))

    def split(self, out: torch.Tensor) -> AdapterOutput:
        """The AdapterOutput of the stacked adapters' output `out` (N, K) (`stacked`)."""
        parts = out.split([lin.out_features for lin in self._layers()], dim=1)
        q = parts[2] + self.identity_quat.to(out.dtype)
        d_o = d_sh = None
        if self.opacity is not None:
            d_o = parts[3]
            d_sh = parts[4].reshape(out.shape[0], self.sh_coeffs, 3)
        return AdapterOutput(parts[0], parts[1], q, d_o, d_sh)

    def force(self, v_c: torch.Tensor) -> torch.Tensor:
        """F = A_mu' v_c: A_mu's weight without its bias (docs/design.md section 4.5), (N, 3)."""
        return v_c @ self.mu.weight.t()


__all__ = ["Adapters", "AdapterOutput"]
