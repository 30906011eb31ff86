"""Where a run starts (docs/training.md, "The recipe"): the initial Gaussians (the dataset's
point cloud, else random points in a box) and the hex-plane's box around them."""

from __future__ import annotations

import numpy as np

from nehad.configtools import ConfigError
from nehad.gaussians import GaussianParameters


def initial_gaussians(train_cfg, scene) -> GaussianParameters:
    """train.init: "points" (the dataset's point cloud, at most train.init_max_points of it),
    "random" (train.init_random_points in [-1.3, 1.3]^3) or "auto" (points when there are
    any)."""
    cfg = train_cfg
    pts = scene.initial_points
    use_points = cfg.init == "points" or (cfg.init == "auto" and pts is not None)
    if not use_points:
        return GaussianParameters.random_in_box(cfg.init_random_points, sh_degree=cfg.sh_degree,
                                                seed=cfg.seed)
    if pts is None:
        raise ConfigError("train.init: 'points' but the dataset has no point cloud")
    colors = scene.initial_colors
    if 0 < cfg.init_max_points < len(pts):
        keep = np.random.default_rng(cfg.seed).choice(len(pts), cfg.init_max_points,
                                                      replace=False)
        pts = pts[keep]
        colors = None if colors is None else colors[keep]
    return GaussianParameters.from_points(pts, colors, sh_degree=cfg.sh_degree, seed=cfg.seed)


def scene_bounds(points: np.ndarray | None) -> np.ndarray:
    """The hex-plane's aabb (2, 3): the initial points' bounds (4DGS), else [-1.3, 1.3]^3."""
    if points is None or len(points) == 0:
        return np.array([[-1.3] * 3, [1.3] * 3], np.float32)
    lo, hi = points.min(0), points.max(0)
    pad = 0.05 * (hi - lo).max()
    return np.stack([lo - pad, hi + pad]).astype(np.float32)


__all__ = ["initial_gaussians", "scene_bounds"]
