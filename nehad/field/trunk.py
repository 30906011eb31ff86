"""Trunk M of the deformation field (paper Sec. "Neural Hamiltonian Deformation Fields":
h_i = M(f_i); docs/design.md section 4.2; 4DGS `feature_out`)."""

from __future__ import annotations

from torch import nn


class Trunk(nn.Sequential):
    """h = M(f): Linear(F, W) then (D - 1) x [ReLU, Linear(W, W)].

    The ReLUs are fine here (docs/design.md section 4.2): the smoothness that v = grad_h F needs is the smoothness of
    F in h, not of h in f; gradients reach the planes through dh/df, which is piecewise linear.
    """

    def __init__(self, in_dim: int, width: int = 64, depth: int = 1):
        layers: list[nn.Module] = [nn.Linear(in_dim, width)]
        for _ in range(depth - 1):
            layers += [nn.ReLU(), nn.Linear(width, width)]
        super().__init__(*layers)
        self.in_dim, self.width, self.depth = in_dim, width, depth


__all__ = ["Trunk"]
