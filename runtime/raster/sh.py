"""Real spherical harmonics up to degree 3 with the standard 3DGS constants (docs/design.md section 3).

rgb = max(sum_k sh_k * basis_k(dir) + 0.5, 0), dir = normalize(mu - camera_centre).
"""

from __future__ import annotations

import numba
import numpy as np

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@numba.njit(inline="always")
def sh_basis(degree, x, y, z, out):
    """Write the (degree+1)^2 basis values for unit direction (x, y, z) into `out`."""
    out[0] = SH_C0
    if degree < 1:
        return
    out[1] = -SH_C1 * y
    out[2] = SH_C1 * z
    out[3] = -SH_C1 * x
    if degree < 2:
        return
    xx, yy, zz = x * x, y * y, z * z
    out[4] = SH_C2[0] * x * y
    out[5] = SH_C2[1] * y * z
    out[6] = SH_C2[2] * (2.0 * zz - xx - yy)
    out[7] = SH_C2[3] * x * z
    out[8] = SH_C2[4] * (xx - yy)
    if degree < 3:
        return
    out[9] = SH_C3[0] * y * (3.0 * xx - yy)
    out[10] = SH_C3[1] * x * y * z
    out[11] = SH_C3[2] * y * (4.0 * zz - xx - yy)
    out[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    out[13] = SH_C3[4] * x * (4.0 * zz - xx - yy)
    out[14] = SH_C3[5] * z * (xx - yy)
    out[15] = SH_C3[6] * x * (xx - 3.0 * yy)


def sh_to_rgb(sh: np.ndarray, dirs: np.ndarray, degree: int) -> np.ndarray:
    """NumPy evaluation for (N, K, 3) coefficients and (N, 3) unit directions (reference/tests)."""
    n = sh.shape[0]
    basis = np.zeros((n, 16), dtype=np.float64)
    for i in range(n):
        sh_basis(degree, dirs[i, 0], dirs[i, 1], dirs[i, 2], basis[i])
    k = (degree + 1) ** 2
    rgb = np.einsum("nk,nkc->nc", basis[:, :k], sh[:, :k].astype(np.float64)) + 0.5
    return np.maximum(rgb, 0.0).astype(np.float32)


@numba.njit(inline="always")
def sh_basis_backward(degree, x, y, z, g, out):
    """Add d(sum_k g_k basis_k)/d(x, y, z) at direction (x, y, z) to out[0:3] (the chain rule
    through `sh_basis`; the direction is not renormalised here)."""
    if degree < 1:
        return
    gx = -SH_C1 * g[3]
    gy = -SH_C1 * g[1]
    gz = SH_C1 * g[2]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        gx += (SH_C2[0] * y * g[4] - 2.0 * SH_C2[2] * x * g[6] + SH_C2[3] * z * g[7]
               + 2.0 * SH_C2[4] * x * g[8])
        gy += (SH_C2[0] * x * g[4] + SH_C2[1] * z * g[5] - 2.0 * SH_C2[2] * y * g[6]
               - 2.0 * SH_C2[4] * y * g[8])
        gz += SH_C2[1] * y * g[5] + 4.0 * SH_C2[2] * z * g[6] + SH_C2[3] * x * g[7]
        if degree >= 3:
            gx += (SH_C3[0] * 6.0 * x * y * g[9] + SH_C3[1] * y * z * g[10]
                   - SH_C3[2] * 2.0 * x * y * g[11] - SH_C3[3] * 6.0 * x * z * g[12]
                   + SH_C3[4] * (4.0 * zz - 3.0 * xx - yy) * g[13]
                   + SH_C3[5] * 2.0 * x * z * g[14] + SH_C3[6] * 3.0 * (xx - yy) * g[15])
            gy += (SH_C3[0] * 3.0 * (xx - yy) * g[9] + SH_C3[1] * x * z * g[10]
                   + SH_C3[2] * (4.0 * zz - xx - 3.0 * yy) * g[11]
                   - SH_C3[3] * 6.0 * y * z * g[12] - SH_C3[4] * 2.0 * x * y * g[13]
                   - SH_C3[5] * 2.0 * y * z * g[14] - SH_C3[6] * 6.0 * x * y * g[15])
            gz += (SH_C3[1] * x * y * g[10] + SH_C3[2] * 8.0 * y * z * g[11]
                   + SH_C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * g[12]
                   + SH_C3[4] * 8.0 * x * z * g[13] + SH_C3[5] * (xx - yy) * g[14])
    out[0] += gx
    out[1] += gy
    out[2] += gz
