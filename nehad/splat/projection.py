"""EWA projection of 3D Gaussians for training, differentiable (docs/design.md section 6).

`project_gaussians_numba` (what training uses) runs the runtime's Numba projection and its
hand-written chain rule (`nehad.runtime.raster.projection.project_backward`) inside a
`torch.autograd.Function`: 1.3 ms instead of 5.8 ms forward and backward for 20k Gaussians
(2 threads).
`project_gaussians_torch` is the same projection in torch ops, the reference that tests hold the
Numba one and its gradients against (autograd).

Sigma = R S S^T R^T; cull z <= 0.2; J with x/z, y/z clamped to 1.3 tan(fov/2);
Sigma2D = J W Sigma W^T J^T + 0.3 I; conic = Sigma2D^-1; radius = ceil(3 sqrt(lambda_max)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from nehad.runtime.raster.projection import (COV2D_DILATION, FRUSTUM_CLAMP, NEAR_PLANE, TILE,
                                             project_backward, project_gaussians)

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


def _np32(t: torch.Tensor) -> np.ndarray:
    """A tensor's values as a contiguous float32 NumPy array on the CPU (for the Numba side)."""
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


class _NumbaProjection(torch.autograd.Function):
    """(means, scales, quats, sh) -> (means2d, conics, colors, depths, radii); depths and radii
    carry no gradient."""

    @staticmethod
    def forward(ctx, means, scales, quats, sh, camera, sh_degree):
        arrays = [_np32(t) for t in (means, scales, quats, sh)]
        no_opacities = np.zeros(0, np.float32)  # they pass through; the projection ignores them
        p = project_gaussians(arrays[0], arrays[1], arrays[2], no_opacities, arrays[3], camera,
                              sh_degree)
        ctx.saved = (arrays, camera, sh_degree, p.radii)
        dev, dt = means.device, means.dtype
        to = lambda a: torch.from_numpy(a).to(dev, dt)  # noqa: E731
        depths, radii = to(p.depths), torch.from_numpy(p.radii).to(dev)
        ctx.mark_non_differentiable(depths, radii)
        return to(p.means2d), to(p.conics), to(p.colors), depths, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_colors, g_depths, g_radii):
        (means, scales, quats, sh), camera, sh_degree, radii = ctx.saved
        n = means.shape[0]
        zero = lambda c: np.zeros((n, c), np.float32)  # noqa: E731
        g = project_backward(means, scales, quats, sh, camera, radii,
                             zero(2) if g_means2d is None else _np32(g_means2d),
                             zero(3) if g_conics is None else _np32(g_conics),
                             zero(3) if g_colors is None else _np32(g_colors), sh_degree)
        ref = next(t for t in (g_means2d, g_conics, g_colors) if t is not None)
        to = lambda a: torch.from_numpy(a).to(ref.device, ref.dtype)  # noqa: E731
        return to(g.means), to(g.scales), to(g.quats), to(g.sh), None, None


def project_gaussians_numba(means, scales, quats, opacities, sh, camera,
                            sh_degree: int | None = None) -> ProjectedTorch:
    """`project_gaussians_torch`'s results and gradients from the Numba projection (module
    doc); opacities pass through."""
    means2d, conics, colors, depths, radii = _NumbaProjection.apply(means, scales, quats, sh,
                                                                    camera, sh_degree)
    return ProjectedTorch(means2d, conics, depths, radii, colors, opacities)
