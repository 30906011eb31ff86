"""EWA projection of 3D Gaussians in torch (differentiable), the twin of
`nehad.runtime.raster.projection` (docs/design.md section 6); tests hold the two against each other.

Sigma = R S S^T R^T; cull z <= 0.2; J with x/z, y/z clamped to 1.3 tan(fov/2);
Sigma2D = J W Sigma W^T J^T + 0.3 I; conic = Sigma2D^-1; radius = ceil(3 sqrt(lambda_max)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from nehad.runtime.raster.projection import COV2D_DILATION, FRUSTUM_CLAMP, NEAR_PLANE, TILE

from .sh import sh_to_rgb


@dataclass
class ProjectedTorch:
    """Screen-space Gaussians as torch tensors. means2d, conics, colors, opacities carry
    gradients; depths is the view z; radii (int32, 0 = culled) is not differentiable."""

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    colors: torch.Tensor
    opacities: torch.Tensor


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), normalised here, to (N, 3, 3) rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(-1, 3, 3)


def project_gaussians_torch(means, scales, quats, opacities, sh, camera,
                            sh_degree: int | None = None) -> ProjectedTorch:
    """Project activated Gaussians (tensors) through a `Camera`; differentiable."""
    dt = means.dtype
    w2c = torch.as_tensor(camera.world_to_camera, dtype=dt, device=means.device)
    rot_w, trans_w = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    width, height = int(camera.width), int(camera.height)

    p_cam = means @ rot_w.T + trans_w
    x, y, z = p_cam.unbind(-1)
    in_front = z > NEAR_PLANE
    z_safe = torch.where(in_front, z, torch.ones_like(z))

    # Sigma2D = T Sigma T^T with T = J W (2x3) and Sigma = M M^T, M = R S: with u, v the rows of
    # T M, Sigma2D = [[u.u, u.v], [u.v, v.v]]. Written elementwise: batched 3x3 matrix products
    # cost torch more than the arithmetic (9 bmm calls per step with their backward).
    rot = quat_to_rotmat(quats)
    m = rot * scales[:, None, :]

    limx = FRUSTUM_CLAMP * width / (2.0 * fx)
    limy = FRUSTUM_CLAMP * height / (2.0 * fy)
    tx = torch.clamp(x / z_safe, -limx, limx) * z_safe
    ty = torch.clamp(y / z_safe, -limy, limy) * z_safe
    inv_z = 1.0 / z_safe
    t0 = (fx * inv_z)[:, None] * rot_w[0] - (fx * tx * inv_z * inv_z)[:, None] * rot_w[2]
    t1 = (fy * inv_z)[:, None] * rot_w[1] - (fy * ty * inv_z * inv_z)[:, None] * rot_w[2]
    u = (t0[:, :, None] * m).sum(1)
    v = (t1[:, :, None] * m).sum(1)
    a = (u * u).sum(-1) + COV2D_DILATION
    b = (u * v).sum(-1)
    c = (v * v).sum(-1) + COV2D_DILATION
    det = a * c - b * b
    ok = in_front & (det > 0)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1)
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], -1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        ntx, nty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        mx, my = means2d[:, 0] - 0.5, means2d[:, 1] - 0.5
        tx0 = torch.clamp(torch.floor((mx - radius) / TILE), 0, ntx)
        tx1 = torch.clamp(torch.floor((mx + radius + TILE - 1) / TILE), 0, ntx)
        ty0 = torch.clamp(torch.floor((my - radius) / TILE), 0, nty)
        ty1 = torch.clamp(torch.floor((my + radius + TILE - 1) / TILE), 0, nty)
        visible = ok & (tx1 > tx0) & (ty1 > ty0)
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)

    stored = int(round(math.sqrt(sh.shape[1]))) - 1
    degree = stored if sh_degree is None else min(int(sh_degree), stored)
    centre = torch.as_tensor(camera.centre, dtype=dt, device=means.device)
    dirs = means - centre
    dirs = dirs / torch.clamp_min(dirs.norm(dim=-1, keepdim=True), 1e-12)
    colors = sh_to_rgb(sh, dirs, degree)
    return ProjectedTorch(means2d, conics, z, radii, colors, opacities)
