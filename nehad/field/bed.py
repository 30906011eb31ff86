"""Boltzmann equilibrium decomposition masks (paper Sec. "Boltzmann Equilibrium Decomposition",
Alg. 1 "Boltzmann equilibrium masks"; docs/design.md section 4.7):

    dd = |mu - mu_eq| / sigma_s,   dtau = (t - t_eq) / sigma_t,
    E_st = (dd^2 + dtau^2) / 2 + lam dd dtau,        M_pos = (1 - gamma) exp(-beta E_st) + gamma,
    E_t = dtau^2 / 2,                                M_scale = (1 - gamma) exp(-beta E_t) + gamma.

The norm is the safe sqrt(|x|^2 + eps): the exact norm has a NaN gradient at mu = mu_eq, which is
where every Gaussian starts (mu_eq is initialised to mu). With |lam| < 1, E_st >= 0, so both masks
lie in [gamma, 1] and equal 1 (up to the eps of the norm) at equilibrium.

`floor="deformation"` reads gamma as the paper's "minimum dynamic responsiveness": the blend
weight 1 - M, not M, is floored at gamma, so M = (1 - gamma) exp(-beta E) lies in [0, 1 - gamma]
and no Gaussian is ever wholly held (docs/design.md section 4.7, `FieldConfig.bed_floor`).
"""

from __future__ import annotations

import torch

from nehad.field.config import FieldConfig


def safe_norm(x: torch.Tensor, eps: float = 1e-12, dim: int = -1,
              keepdim: bool = True) -> torch.Tensor:
    """sqrt(|x|^2 + eps): finite gradient x / sqrt(|x|^2 + eps) everywhere (0 at x = 0)."""
    return torch.sqrt((x * x).sum(dim=dim, keepdim=keepdim) + eps)


def position_mask(mu: torch.Tensor, mu_eq: torch.Tensor, t: torch.Tensor, t_eq: torch.Tensor, *,
                  sigma_s: float, sigma_t: float, beta: float = 1.0, gamma: float = 0.05,
                  lam: float = 0.5, eps: float = 1e-12, dim: int = -1,
                  floor: str = "mask") -> torch.Tensor:
    """M_pos (N, 1) from mu, mu_eq (N, 3), t (N, 1) or broadcastable, t_eq (N, 1). `dim` is the
    xyz axis of mu (the export passes (3, N) columns with dim=0 and gets (1, N)); `floor`: what
    gamma floors, the mask or the deformation (module doc)."""
    dd = safe_norm(mu - mu_eq, eps, dim=dim) / sigma_s
    dtau = (t - t_eq) / sigma_t
    e_st = 0.5 * (dd * dd + dtau * dtau) + lam * dd * dtau
    return _boltzmann(e_st, beta, gamma, floor)


def scale_mask(t: torch.Tensor, t_eq: torch.Tensor, *, sigma_t: float, beta: float = 1.0,
               gamma: float = 0.05, floor: str = "mask") -> torch.Tensor:
    """M_scale (N, 1): temporal-only decomposition."""
    dtau = (t - t_eq) / sigma_t
    return _boltzmann(0.5 * dtau * dtau, beta, gamma, floor)


def _boltzmann(energy: torch.Tensor, beta: float, gamma: float, floor: str) -> torch.Tensor:
    """(1 - gamma) exp(-beta E), plus gamma when gamma floors the mask (paper Eq. M_pos)."""
    held = (1.0 - gamma) * torch.exp(-beta * energy)
    return held + gamma if floor == "mask" else held


def bed_masks(mu: torch.Tensor, mu_eq: torch.Tensor, t: torch.Tensor, t_eq: torch.Tensor,
              cfg: FieldConfig, extent: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(M_pos, M_scale), each (N, 1), with sigma_s = cfg.sigma_s_fraction * extent."""
    sigma_s = cfg.sigma_s_fraction * float(extent)
    m_pos = position_mask(mu, mu_eq, t, t_eq, sigma_s=sigma_s, sigma_t=cfg.sigma_t,
                          beta=cfg.beta, gamma=cfg.gamma, lam=cfg.lam, eps=cfg.norm_eps,
                          floor=cfg.bed_floor)
    m_scale = scale_mask(t, t_eq, sigma_t=cfg.sigma_t, beta=cfg.beta, gamma=cfg.gamma,
                         floor=cfg.bed_floor)
    return m_pos, m_scale


__all__ = ["safe_norm", "position_mask", "scale_mask", "bed_masks"]
