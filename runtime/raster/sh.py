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
