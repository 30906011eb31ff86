"""The activated Gaussian set every renderer consumes (docs/design.md section 7 output layout)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Standard 3DGS spherical-harmonics constants (docs/design.md section 3).
SH_C0 = 0.28209479177387814


@dataclass
class GaussianCloud:
    """N Gaussians in world space, parameters already activated.

    means (N, 3) float32; scales (N, 3) float32, positive (exp of log-scales);
    quats (N, 4) float32, unit, (w, x, y, z); opacities (N,) float32 in (0, 1);
    sh (N, K, 3) float32 with K = (degree + 1)^2, coefficient-major then channel.
    """

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray

    def __post_init__(self):
        n = self.means.shape[0]
        self.means = np.ascontiguousarray(self.means, dtype=np.float32).reshape(n, 3)
        self.scales = np.ascontiguousarray(self.scales, dtype=np.float32).reshape(n, 3)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32).reshape(n, 4)
        self.opacities = np.ascontiguousarray(self.opacities, dtype=np.float32).reshape(n)
        sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        # (N, K, 3); an empty cloud keeps its K (reshape cannot infer it from 0 values)
        k = sh.shape[1] if sh.ndim == 3 else (sh.size // (3 * n) if n else 1)
        self.sh = sh.reshape(n, k, 3)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        k = self.sh.shape[1]
        deg = int(round(np.sqrt(k))) - 1
        if (deg + 1) ** 2 != k:
            raise ValueError(f"sh: {k} coefficients per channel is not (degree+1)^2")
        return deg

    def base_rgb(self) -> np.ndarray:
        """(N, 3) float64 view-independent colour, the SH degree-0 term 0.5 + C0 dc, clipped
        to [0, 1] (what .splat files, the viewer and the tracks' colour test use)."""
        return np.clip(0.5 + SH_C0 * self.sh[:, 0, :].astype(np.float64), 0.0, 1.0)
