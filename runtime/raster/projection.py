"""Projection of 3D Gaussians to screen space (EWA splatting), NumPy/Numba side (docs/design.md section 6).

Its torch twin is `nehad.splat.projection`; tests hold the two against each other.
Sigma = R S S^T R^T; cull z <= 0.2; J with x/z, y/z clamped to 1.3 tan(fov/2);
Sigma2D = J W Sigma W^T J^T + 0.3 I; conic = Sigma2D^-1; radius = ceil(3 sqrt(lambda_max)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .sh import sh_basis

NEAR_PLANE = 0.2
COV2D_DILATION = 0.3
FRUSTUM_CLAMP = 1.3
TILE = 16
#: Gaussians per parallel task of the per-Gaussian stages (projection, tile rectangles): tasks
#: are handed out as threads finish, so a thread slowed by another process on its core takes
#: fewer of them instead of holding the others at the end (docs/performance.md#threads).
GAUSSIANS_PER_TASK = 2048


@dataclass
class Projected:
    """Screen-space Gaussians: the rasterizer's inputs (docs/design.md section 6).

    means2d (N, 2) pixels; conics (N, 3) = (a, b, c) of [[a, b], [b, c]]; depths (N,) view z;
    radii (N,) int32, 0 for culled Gaussians; colors (N, 3); opacities (N,).
    """

    means2d: np.ndarray
    conics: np.ndarray
    depths: np.ndarray
    radii: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray


@numba.njit(parallel=True, cache=True)
def _project_kernel(means, scales, quats, sh, degree, w2c, fx, fy, cx, cy, width, height,
                    means2d, conics, depths, radii, colors):
    n = means.shape[0]
    r00, r01, r02, t0 = w2c[0, 0], w2c[0, 1], w2c[0, 2], w2c[0, 3]
    r10, r11, r12, t1 = w2c[1, 0], w2c[1, 1], w2c[1, 2], w2c[1, 3]
    r20, r21, r22, t2 = w2c[2, 0], w2c[2, 1], w2c[2, 2], w2c[2, 3]
    # camera centre = -R^T t
    ccx = -(r00 * t0 + r10 * t1 + r20 * t2)
    ccy = -(r01 * t0 + r11 * t1 + r21 * t2)
    ccz = -(r02 * t0 + r12 * t1 + r22 * t2)
    limx = FRUSTUM_CLAMP * width / (2.0 * fx)
    limy = FRUSTUM_CLAMP * height / (2.0 * fy)
    ntile_x = (width + TILE - 1) // TILE
    ntile_y = (height + TILE - 1) // TILE
    k = (degree + 1) * (degree + 1)
    for i in numba.prange(n):
        radii[i] = 0
        px, py, pz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        x = r00 * px + r01 * py + r02 * pz + t0
        y = r10 * px + r11 * py + r12 * pz + t1
        z = r20 * px + r21 * py + r22 * pz + t2
        depths[i] = z
        if not (z > NEAR_PLANE):
            continue
        # rotation of the Gaussian from its unit quaternion (w, x, y, z)
        qw, qx, qy, qz = np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]), np.float64(quats[i, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        m00 = 1 - 2 * (qy * qy + qz * qz); m01 = 2 * (qx * qy - qw * qz); m02 = 2 * (qx * qz + qw * qy)
        m10 = 2 * (qx * qy + qw * qz); m11 = 1 - 2 * (qx * qx + qz * qz); m12 = 2 * (qy * qz - qw * qx)
        m20 = 2 * (qx * qz - qw * qy); m21 = 2 * (qy * qz + qw * qx); m22 = 1 - 2 * (qx * qx + qy * qy)
        sx, sy, sz = np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2])
        # M = R S ; Sigma = M M^T
        a00, a01, a02 = m00 * sx, m01 * sy, m02 * sz
        a10, a11, a12 = m10 * sx, m11 * sy, m12 * sz
        a20, a21, a22 = m20 * sx, m21 * sy, m22 * sz
        s00 = a00 * a00 + a01 * a01 + a02 * a02
        s01 = a00 * a10 + a01 * a11 + a02 * a12
        s02 = a00 * a20 + a01 * a21 + a02 * a22
        s11 = a10 * a10 + a11 * a11 + a12 * a12
        s12 = a10 * a20 + a11 * a21 + a12 * a22
        s22 = a20 * a20 + a21 * a21 + a22 * a22
        # EWA Jacobian with the clamped screen position
        tx = min(max(x / z, -limx), limx) * z
        ty = min(max(y / z, -limy), limy) * z
        j00 = fx / z
        j02 = -fx * tx / (z * z)
        j11 = fy / z
        j12 = -fy * ty / (z * z)
        # T = J W (2x3)
        u0 = j00 * r00 + j02 * r20; u1 = j00 * r01 + j02 * r21; u2 = j00 * r02 + j02 * r22
        v0 = j11 * r10 + j12 * r20; v1 = j11 * r11 + j12 * r21; v2 = j11 * r12 + j12 * r22
        # Sigma2D = T Sigma T^T
        su0 = s00 * u0 + s01 * u1 + s02 * u2
        su1 = s01 * u0 + s11 * u1 + s12 * u2
        su2 = s02 * u0 + s12 * u1 + s22 * u2
        sv0 = s00 * v0 + s01 * v1 + s02 * v2
        sv1 = s01 * v0 + s11 * v1 + s12 * v2
        sv2 = s02 * v0 + s12 * v1 + s22 * v2
        ca = u0 * su0 + u1 * su1 + u2 * su2 + COV2D_DILATION
        cb = u0 * sv0 + u1 * sv1 + u2 * sv2
        cc = v0 * sv0 + v1 * sv1 + v2 * sv2 + COV2D_DILATION
        det = ca * cc - cb * cb
        if not (det > 0.0):
            continue
        mid = 0.5 * (ca + cc)
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        radius = math.ceil(3.0 * math.sqrt(lam))
        mx = fx * x / z + cx
        my = fy * y / z + cy
        # tiles touched by the 3-sigma box (3DGS getRect, pixel centres at i + 0.5)
        tx0 = min(ntile_x, max(0, int(math.floor((mx - 0.5 - radius) / TILE))))
        tx1 = min(ntile_x, max(0, int(math.floor((mx - 0.5 + radius + TILE - 1) / TILE))))
        ty0 = min(ntile_y, max(0, int(math.floor((my - 0.5 - radius) / TILE))))
        ty1 = min(ntile_y, max(0, int(math.floor((my - 0.5 + radius + TILE - 1) / TILE))))
        if tx1 <= tx0 or ty1 <= ty0:
            continue
        radii[i] = radius
        means2d[i, 0] = mx
        means2d[i, 1] = my
        conics[i, 0] = cc / det
        conics[i, 1] = -cb / det
        conics[i, 2] = ca / det
        # view-dependent colour
        dx, dy, dz = px - ccx, py - ccy, pz - ccz
        dn = math.sqrt(dx * dx + dy * dy + dz * dz)
        dn = max(dn, 1e-12)
        basis = np.empty(16, dtype=np.float64)
        sh_basis(degree, dx / dn, dy / dn, dz / dn, basis)
        for ch in range(3):
            acc = 0.5
            for j in range(k):
                acc += basis[j] * sh[i, j, ch]
            colors[i, ch] = max(acc, 0.0)


def project_gaussians(means, scales, quats, opacities, sh, camera, sh_degree=None) -> Projected:
    """Project activated Gaussians (see `GaussianCloud`) through a `Camera`."""
    n = means.shape[0]
    stored = int(round(math.sqrt(sh.shape[1]))) - 1
    degree = stored if sh_degree is None else min(int(sh_degree), stored)
    means2d = np.zeros((n, 2), np.float32)
    conics = np.zeros((n, 3), np.float32)
    depths = np.zeros(n, np.float32)
    radii = np.zeros(n, np.int32)
    colors = np.zeros((n, 3), np.float32)
    with numba.parallel_chunksize(GAUSSIANS_PER_TASK):
        _project_kernel(np.ascontiguousarray(means, np.float32),
                        np.ascontiguousarray(scales, np.float32),
                        np.ascontiguousarray(quats, np.float32), np.ascontiguousarray(sh, np.float32),
                        degree, np.ascontiguousarray(camera.world_to_camera, np.float64),
                        float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                        int(camera.width), int(camera.height), means2d, conics, depths, radii,
                        colors)
    return Projected(means2d, conics, depths, radii, colors,
                     np.ascontiguousarray(opacities, np.float32))
