"""Benchmark scenes shared by the bench scripts (the scene of ../shared/notes/cpu-raster.md)."""

from __future__ import annotations

import numpy as np

from nehad.runtime.cameras import Camera
from nehad.runtime.gaussians import GaussianCloud


def random_cloud(n: int, seed: int = 0, sh_degree: int = 0) -> GaussianCloud:
    """Means uniform in [-1, 1]^3, world std 0.01-0.04, random rotations, opacity 0.1-0.9."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    k = (sh_degree + 1) ** 2
    sh = np.zeros((n, k, 3))
    sh[:, 0] = (rng.uniform(0, 1, (n, 3)) - 0.5) / 0.28209479177387814
    if k > 1:
        sh[:, 1:] = rng.normal(scale=0.1, size=(n, k - 1, 3))
    return GaussianCloud(rng.uniform(-1, 1, (n, 3)), rng.uniform(0.01, 0.04, (n, 3)), q,
                         rng.uniform(0.1, 0.9, n), sh)


def orbit_camera(size: int, distance: float = 3.5, fov_deg: float = 50.0,
                 azimuth_deg: float = 30.0, elevation_deg: float = 20.0) -> Camera:
    """A square camera on a sphere around the origin, looking at it (OpenCV axes)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    centre = distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, centre
    f = 0.5 * size / np.tan(np.radians(fov_deg) / 2)
    return Camera.from_camera_to_world(c2w, size, size, f, f, convention="opencv")
