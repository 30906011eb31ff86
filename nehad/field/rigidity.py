"""Local rigidity on rotation (paper Sec. "Local Rigidity Regularization", Alg. 1; docs/design.md section 4.8):

    dw = q_0, dg = q_1:3, phi = 2 atan2(|dg|, dw), phi' = phi_max tanh(phi / phi_max),
    dr' = (cos(phi'/2), sin(phi'/2) dg / |dg|),  r' = N(r (x) dr').

ONNX has no Atan2, so atan2(y, x) for y > 0 is written with the half-angle identity
tan(theta/2) = y / (rho + x) = (rho - x) / y, rho = sqrt(x^2 + y^2), choosing the branch whose
denominator cannot vanish (Atan, Sqrt, Div, Where only). |dg| is the safe norm sqrt(|dg|^2 + eps),
so dg = 0 gives the identity rotation with finite gradients (sin(phi'/2) / |dg| -> 1 / dw).
Quaternions are (w, x, y, z) (docs/design.md section 3).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from nehad.field.bed import safe_norm


def quat_multiply(a: torch.Tensor, b: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Hamilton product a (x) b of (..., 4) quaternions (w, x, y, z) (components along `dim`)."""
    aw, ax, ay, az = a.unbind(dim)
    bw, bx, by, bz = b.unbind(dim)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=dim)


def safe_normalize(q: torch.Tensor, eps: float = 1e-12, dim: int = -1) -> torch.Tensor:
    """N(q) = q / sqrt(|q|^2 + eps) along `dim` (the last axis by default)."""
    return q / safe_norm(q, eps, dim=dim)


def atan2_positive_y(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """atan2(y, x) in (0, pi) for y > 0, without an Atan2 op (ONNX-exportable):
    2 atan(y / (rho + x)) where x >= 0, 2 atan((rho - x) / y) where x < 0. The unused branch's
    denominator is replaced by 1 so neither branch produces inf/NaN (nor NaN gradients)."""
    rho = torch.sqrt(x * x + y * y)
    pos = x >= 0
    den = torch.where(pos, rho + x, torch.ones_like(x))
    tan_half = torch.where(pos, y / den, (rho - x) / y)
    return 2.0 * torch.atan(tan_half)


class RotationDelta(NamedTuple):
    dr: torch.Tensor  # (N, 4) unit quaternion dr'
    phi: torch.Tensor  # (N, 1) raw angle of q, in [0, 2 pi]
    phi_clamped: torch.Tensor  # (N, 1) phi' = phi_max tanh(phi / phi_max) < phi_max


def clamp_rotation_delta(q: torch.Tensor, phi_max: float, eps: float = 1e-12,
                         dim: int = -1) -> RotationDelta:
    """Rigidity clamp of a (not necessarily unit) quaternion delta q (N, 4) -> unit dr'.
    phi depends only on q's direction (scale-invariant). `dim` is the quaternion axis (the
    export passes (4, N) columns with dim=0)."""
    dw, dg = q.narrow(dim, 0, 1), q.narrow(dim, 1, 3)
    g_norm = safe_norm(dg, eps, dim=dim)
    phi = 2.0 * atan2_positive_y(g_norm, dw)
    phi_c = phi_max * torch.tanh(phi / phi_max)
    half = 0.5 * phi_c
    dr = torch.cat([torch.cos(half), torch.sin(half) * dg / g_norm], dim=dim)
    return RotationDelta(dr, phi, phi_c)


def rotation_angle(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Angle in [0, pi] of the rotation represented by q (N, 4) (q and -q are the same)."""
    g = safe_norm(q[..., 1:], eps)
    return 2.0 * atan2_positive_y(g, q[..., :1].abs())


__all__ = ["quat_multiply", "safe_normalize", "atan2_positive_y", "clamp_rotation_delta",
           "rotation_angle", "RotationDelta"]
