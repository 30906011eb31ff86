"""Spherical-harmonics colour in torch, the twin of `nehad.runtime.raster.sh` (docs/design.md section 3)."""

from __future__ import annotations

import torch

from nehad.runtime.raster.sh import SH_C0, SH_C1, SH_C2, SH_C3


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, (degree+1)^2) real SH basis for unit directions (N, 3), 3DGS constants and signs."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy),
                SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
        if degree >= 3:
            out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z,
                    SH_C3[2] * y * (4 * zz - xx - yy), SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                    SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                    SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


def sh_to_rgb(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """rgb = max(sum_k sh_k basis_k(dir) + 0.5, 0) for sh (N, K, 3), using the first
    (degree+1)^2 coefficients."""
    k = (degree + 1) ** 2
    basis = sh_basis(dirs, degree)
    return torch.clamp_min(torch.einsum("nk,nkc->nc", basis, sh[:, :k]) + 0.5, 0.0)
