"""Projection of 3D Gaussians to screen space (EWA splatting), NumPy/Numba side (docs/design.md section 6).

Its torch twin is `nehad.splat.projection`; tests hold the two against each other.
Sigma = R S S^T R^T; cull z <= 0.2; J with x/z, y/z clamped to 1.3 tan(fov/2);
Sigma2D = J W Sigma W^T J^T + 0.3 I; conic = Sigma2D^-1; radius = ceil(3 sqrt(lambda_max)).
`project_backward` is its chain rule (the gradients torch autograd gives through the twin, which
tests/test_raster.py checks), so that training needs no torch graph for the projection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .sh import sh_basis, sh_basis_backward

NEAR_PLANE = 0.2
COV2D_DILATION = 0.3
FRUSTUM_CLAMP = 1.3
TILE = 16
#: Gaussians per task of the projection's backward kernel, which allocates its scratch arrays
#: once per task instead of once per Gaussian.
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


@numba.njit(inline="always")
def _view(w2c, fx, fy, width, height):
    """The world-to-camera rotation (row by row) and translation, the camera centre -R^T t and
    the frustum clamp's limits on x/z and y/z."""
    r00, r01, r02, t0 = w2c[0, 0], w2c[0, 1], w2c[0, 2], w2c[0, 3]
    r10, r11, r12, t1 = w2c[1, 0], w2c[1, 1], w2c[1, 2], w2c[1, 3]
    r20, r21, r22, t2 = w2c[2, 0], w2c[2, 1], w2c[2, 2], w2c[2, 3]
    ccx = -(r00 * t0 + r10 * t1 + r20 * t2)
    ccy = -(r01 * t0 + r11 * t1 + r21 * t2)
    ccz = -(r02 * t0 + r12 * t1 + r22 * t2)
    limx = FRUSTUM_CLAMP * width / (2.0 * fx)
    limy = FRUSTUM_CLAMP * height / (2.0 * fy)
    return (r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2, ccx, ccy, ccz, limx, limy)


@numba.njit(inline="always")
def _rotation(qw, qx, qy, qz):
    """Rotation matrix (row by row) of a unit quaternion (w, x, y, z)."""
    return (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
            2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
            2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy))


@numba.njit(inline="always")
def _unit_quaternion(quats, i):
    """Gaussian i's quaternion (w, x, y, z) normalised, and its norm."""
    qw, qx, qy, qz = (np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                      np.float64(quats[i, 3]))
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw / qn, qx / qn, qy / qn, qz / qn, qn


@numba.njit(inline="always")
def _ewa_rows(x, y, z, fx, fy, limx, limy, w2c):
    """The clamped screen position (tx, ty) (x/z and y/z limited to the frustum clamp, times z)
    and the two rows u, v of T = J W, J the EWA Jacobian at it."""
    tx = min(max(x / z, -limx), limx) * z
    ty = min(max(y / z, -limy), limy) * z
    j00 = fx / z
    j02 = -fx * tx / (z * z)
    j11 = fy / z
    j12 = -fy * ty / (z * z)
    return (tx, ty,
            j00 * w2c[0, 0] + j02 * w2c[2, 0], j00 * w2c[0, 1] + j02 * w2c[2, 1],
            j00 * w2c[0, 2] + j02 * w2c[2, 2],
            j11 * w2c[1, 0] + j12 * w2c[2, 0], j11 * w2c[1, 1] + j12 * w2c[2, 1],
            j11 * w2c[1, 2] + j12 * w2c[2, 2])


@numba.njit(inline="always")
def _sh_sum(basis, sh, i, ch, k):
    """0.5 + sum_j basis_j sh[i, j, ch] over the first k coefficients: channel ch's colour
    before the clamp at 0."""
    acc = 0.5
    for j in range(k):
        acc += basis[j] * sh[i, j, ch]
    return acc


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _degree(sh, sh_degree) -> int:
    """The SH degree drawn: the requested one, at most the stored one."""
    stored = int(round(math.sqrt(sh.shape[1]))) - 1
    return stored if sh_degree is None else min(int(sh_degree), stored)


@numba.njit(parallel=True, cache=True)
def _project_kernel(means, scales, quats, sh, degree, w2c, fx, fy, cx, cy, width, height,
                    means2d, conics, depths, radii, colors):
    n = means.shape[0]
    (r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2, ccx, ccy, ccz, limx,
     limy) = _view(w2c, fx, fy, width, height)
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
        qw, qx, qy, qz, _ = _unit_quaternion(quats, i)
        m00, m01, m02, m10, m11, m12, m20, m21, m22 = _rotation(qw, qx, qy, qz)
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
        # T = J W (2x3), J the EWA Jacobian at the clamped screen position
        _, _, u0, u1, u2, v0, v1, v2 = _ewa_rows(x, y, z, fx, fy, limx, limy, w2c)
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
            colors[i, ch] = max(_sh_sum(basis, sh, i, ch, k), 0.0)


@numba.njit(parallel=True, cache=True)
def _project_backward_kernel(means, scales, quats, sh, degree, w2c, fx, fy, width, height, radii,
                             g_means2d, g_conics, g_colors, g_means, g_scales, g_quats, g_sh):
    n = means.shape[0]
    (r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2, ccx, ccy, ccz, limx,
     limy) = _view(w2c, fx, fy, width, height)
    k = (degree + 1) * (degree + 1)
    per = GAUSSIANS_PER_TASK
    for task in numba.prange((n + per - 1) // per):
        # scratch arrays once per task (allocating them per Gaussian costs more than the maths)
        rot = np.empty((3, 3))
        g_rot = np.empty((3, 3))
        vecs = np.empty((11, 3))  # s, u, v, U, V, gU, gV, gu, gv, g_mean, g_dir
        basis = np.empty(16)
        g_basis = np.empty(16)
        s, u, v, uu, vv = vecs[0], vecs[1], vecs[2], vecs[3], vecs[4]
        g_uu, g_vv, g_u, g_v, gp, g_dir = vecs[5], vecs[6], vecs[7], vecs[8], vecs[9], vecs[10]
        for i in range(task * per, min(n, (task + 1) * per)):
            vecs[:, :] = 0.0
            g_basis[:] = 0.0
            if radii[i] <= 0:  # culled: the rasterizer gave it no gradient
                continue
            px, py, pz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            x = r00 * px + r01 * py + r02 * pz + t0
            y = r10 * px + r11 * py + r12 * pz + t1
            z = r20 * px + r21 * py + r22 * pz + t2
            # --- the forward again (as _project_kernel) ---
            qw, qx, qy, qz, qn = _unit_quaternion(quats, i)
            (rot[0, 0], rot[0, 1], rot[0, 2], rot[1, 0], rot[1, 1], rot[1, 2], rot[2, 0],
             rot[2, 1], rot[2, 2]) = _rotation(qw, qx, qy, qz)
            for kk in range(3):
                s[kk] = np.float64(scales[i, kk])
            rx, ry = x / z, y / z
            tx, ty, u[0], u[1], u[2], v[0], v[1], v[2] = _ewa_rows(x, y, z, fx, fy, limx, limy,
                                                                   w2c)
            # U = M^T u, V = M^T v with M = R S: Sigma2D = [[U.U, U.V], [U.V, V.V]] + 0.3 I
            for kk in range(3):
                for ii in range(3):
                    uu[kk] += u[ii] * rot[ii, kk] * s[kk]
                    vv[kk] += v[ii] * rot[ii, kk] * s[kk]
            ca = uu[0] * uu[0] + uu[1] * uu[1] + uu[2] * uu[2] + COV2D_DILATION
            cb = uu[0] * vv[0] + uu[1] * vv[1] + uu[2] * vv[2]
            cc = vv[0] * vv[0] + vv[1] * vv[1] + vv[2] * vv[2] + COV2D_DILATION
            det = ca * cc - cb * cb
            # --- conic = (cc, -cb, ca) / det ---
            g0, g1, g2 = (np.float64(g_conics[i, 0]), np.float64(g_conics[i, 1]),
                          np.float64(g_conics[i, 2]))
            det2 = det * det
            ga = (-cc * cc * g0 + cb * cc * g1 - cb * cb * g2) / det2
            gb = (2.0 * cb * cc * g0 - (det + 2.0 * cb * cb) * g1 + 2.0 * ca * cb * g2) / det2
            gc = (-cb * cb * g0 + ca * cb * g1 - ca * ca * g2) / det2
            for kk in range(3):
                g_uu[kk] = 2.0 * ga * uu[kk] + gb * vv[kk]
                g_vv[kk] = 2.0 * gc * vv[kk] + gb * uu[kk]
            # through U_k = sum_i u_i R_ik s_k
            for kk in range(3):
                g_s = 0.0
                for ii in range(3):
                    g_m = u[ii] * g_uu[kk] + v[ii] * g_vv[kk]  # d/d M_ik
                    g_s += rot[ii, kk] * g_m
                    g_rot[ii, kk] = g_m * s[kk]
                    g_u[ii] += rot[ii, kk] * s[kk] * g_uu[kk]
                    g_v[ii] += rot[ii, kk] * s[kk] * g_vv[kk]
                g_scales[i, kk] = g_s
            # rotation of the normalised quaternion, then the normalisation
            gw = 2.0 * (-qz * g_rot[0, 1] + qy * g_rot[0, 2] + qz * g_rot[1, 0] - qx * g_rot[1, 2]
                        - qy * g_rot[2, 0] + qx * g_rot[2, 1])
            gx = 2.0 * (qy * g_rot[0, 1] + qz * g_rot[0, 2] + qy * g_rot[1, 0]
                        - 2.0 * qx * g_rot[1, 1] - qw * g_rot[1, 2] + qz * g_rot[2, 0]
                        + qw * g_rot[2, 1] - 2.0 * qx * g_rot[2, 2])
            gy = 2.0 * (-2.0 * qy * g_rot[0, 0] + qx * g_rot[0, 1] + qw * g_rot[0, 2]
                        + qx * g_rot[1, 0] + qz * g_rot[1, 2] - qw * g_rot[2, 0] + qz * g_rot[2, 1]
                        - 2.0 * qy * g_rot[2, 2])
            gz = 2.0 * (-2.0 * qz * g_rot[0, 0] - qw * g_rot[0, 1] + qx * g_rot[0, 2]
                        + qw * g_rot[1, 0] - 2.0 * qz * g_rot[1, 1] + qy * g_rot[1, 2]
                        + qx * g_rot[2, 0] + qy * g_rot[2, 1])
            dot = qw * gw + qx * gx + qy * gy + qz * gz
            g_quats[i, 0] = (gw - qw * dot) / qn
            g_quats[i, 1] = (gx - qx * dot) / qn
            g_quats[i, 2] = (gy - qy * dot) / qn
            g_quats[i, 3] = (gz - qz * dot) / qn
            # through T = J W: u = j00 W0 + j02 W2, v = j11 W1 + j12 W2
            g_j00 = r00 * g_u[0] + r01 * g_u[1] + r02 * g_u[2]
            g_j02 = r20 * g_u[0] + r21 * g_u[1] + r22 * g_u[2]
            g_j11 = r10 * g_v[0] + r11 * g_v[1] + r12 * g_v[2]
            g_j12 = r20 * g_v[0] + r21 * g_v[1] + r22 * g_v[2]
            gzc = (-fx * g_j00 - fy * g_j11) / (z * z) \
                + 2.0 * (fx * tx * g_j02 + fy * ty * g_j12) / (z * z * z)
            g_tx = -fx * g_j02 / (z * z)
            g_ty = -fy * g_j12 / (z * z)
            gxc = 0.0
            gyc = 0.0
            # tx = clamp(x / z, -limx, limx) z: x inside the clamp passes, else tx = +-limx z
            if -limx <= rx <= limx:
                gxc += g_tx
            else:
                gzc += (limx if rx > 0 else -limx) * g_tx
            if -limy <= ry <= limy:
                gyc += g_ty
            else:
                gzc += (limy if ry > 0 else -limy) * g_ty
            # mean2d = (fx x / z + cx, fy y / z + cy)
            gmx, gmy = np.float64(g_means2d[i, 0]), np.float64(g_means2d[i, 1])
            gxc += fx / z * gmx
            gyc += fy / z * gmy
            gzc -= (fx * x * gmx + fy * y * gmy) / (z * z)
            gp[0] = r00 * gxc + r10 * gyc + r20 * gzc
            gp[1] = r01 * gxc + r11 * gyc + r21 * gzc
            gp[2] = r02 * gxc + r12 * gyc + r22 * gzc
            # colour = max(sum_k basis_k(dir) sh_k + 0.5, 0), dir = (mean - centre) / |...|
            dx, dy, dz = px - ccx, py - ccy, pz - ccz
            dn = math.sqrt(dx * dx + dy * dy + dz * dz)
            dnc = max(dn, 1e-12)
            ux, uy, uz = dx / dnc, dy / dnc, dz / dnc
            sh_basis(degree, ux, uy, uz, basis)
            for ch in range(3):
                acc = _sh_sum(basis, sh, i, ch, k)
                gcol = np.float64(g_colors[i, ch]) if acc >= 0.0 else 0.0
                for j in range(k):
                    g_sh[i, j, ch] = basis[j] * gcol
                    g_basis[j] += np.float64(sh[i, j, ch]) * gcol
            sh_basis_backward(degree, ux, uy, uz, g_basis, g_dir)
            if dn > 1e-12:
                along = ux * g_dir[0] + uy * g_dir[1] + uz * g_dir[2]
                gp[0] += (g_dir[0] - ux * along) / dn
                gp[1] += (g_dir[1] - uy * along) / dn
                gp[2] += (g_dir[2] - uz * along) / dn
            g_means[i, 0] = gp[0]
            g_means[i, 1] = gp[1]
            g_means[i, 2] = gp[2]


@dataclass
class ProjectionGradients:
    means: np.ndarray  # (N, 3)
    scales: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4)
    sh: np.ndarray  # (N, K, 3): zero beyond the degree used


def project_backward(means, scales, quats, sh, camera, radii, g_means2d, g_conics, g_colors,
                     sh_degree=None) -> ProjectionGradients:
    """Gradients of a loss w.r.t. the activated 3D parameters, given its gradients w.r.t. the
    outputs of `project_gaussians` (same inputs and camera; culled Gaussians get zero)."""
    n = means.shape[0]
    degree = _degree(sh, sh_degree)
    g_means = np.zeros((n, 3), np.float32)
    g_scales = np.zeros((n, 3), np.float32)
    g_quats = np.zeros((n, 4), np.float32)
    g_sh = np.zeros(sh.shape, np.float32)
    _project_backward_kernel(_f32(means), _f32(scales), _f32(quats), _f32(sh), degree,
                             np.ascontiguousarray(camera.world_to_camera, np.float64),
                             float(camera.fx), float(camera.fy), int(camera.width),
                             int(camera.height), np.ascontiguousarray(radii, np.int32),
                             _f32(g_means2d), _f32(g_conics), _f32(g_colors), g_means, g_scales,
                             g_quats, g_sh)
    return ProjectionGradients(g_means, g_scales, g_quats, g_sh)


def project_gaussians(means, scales, quats, opacities, sh, camera, sh_degree=None) -> Projected:
    """Project activated Gaussians (see `GaussianCloud`) through a `Camera`."""
    n = means.shape[0]
    degree = _degree(sh, sh_degree)
    means2d = np.zeros((n, 2), np.float32)
    conics = np.zeros((n, 3), np.float32)
    depths = np.zeros(n, np.float32)
    radii = np.zeros(n, np.int32)
    colors = np.zeros((n, 3), np.float32)
    _project_kernel(_f32(means), _f32(scales), _f32(quats), _f32(sh),
                    degree, np.ascontiguousarray(camera.world_to_camera, np.float64),
                    float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                    int(camera.width), int(camera.height), means2d, conics, depths, radii, colors)
    return Projected(means2d, conics, depths, radii, colors,
                     np.ascontiguousarray(opacities, np.float32))
