"""The training views of a run: a split's cameras, images (torch tensors, composited over the
load background), times and alphas (`Views`), at another resolution (`downscale_views`, the
resolution warm-up of docs/training.md), and the background arithmetic of training over another
colour (`recomposite`, `resolve_background`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nehad.data.common import DNeRFScene, area_downscale, downscale_camera


@dataclass
class Views:
    cameras: list
    images: list  # (H, W, 3) float32 tensors, composited over the load background
    times: list
    alphas: list  # (H, W, 1) float32 tensors, or None for images without alpha


def views_of(scene: DNeRFScene, split: str) -> Views:
    """The frames of `split` as training views."""
    frames = scene.frames[split]
    return Views([f.camera for f in frames],
                 [torch.from_numpy(np.ascontiguousarray(f.image)) for f in frames],
                 [float(f.camera.time or 0.0) for f in frames],
                 [None if f.alpha is None else torch.from_numpy(f.alpha)[:, :, None]
                  for f in frames])


def downscale_views(views: Views, factor: int) -> Views:
    """`views` area-downscaled by an integer factor, cameras to match, as the dataset readers
    downscale (`nehad.data.common.area_downscale`: a remainder at the right/bottom edge is
    cropped)."""
    def pool(img: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(area_downscale(img.numpy(), factor))

    return Views([downscale_camera(c, factor) for c in views.cameras],
                 [pool(im) for im in views.images], list(views.times),
                 [None if a is None else pool(a) for a in views.alphas])


def recomposite(image: torch.Tensor, alpha: torch.Tensor, old_bg, new_bg) -> torch.Tensor:
    """An image composited over `old_bg`, composited over `new_bg` instead:
    rgb + (new - old)(1 - a) (the loader adds bg (1 - a) to premultiplied colour)."""
    delta = torch.as_tensor(np.asarray(new_bg, np.float32) - np.asarray(old_bg, np.float32))
    return image + delta * (1.0 - alpha)


def resolve_background(configured, scene_has_alpha: bool) -> tuple[float, float, float]:
    """The colour a run renders over: data.background when set, else white for scenes with
    alpha (the D-NeRF convention) and black for the others."""
    if configured is not None:
        return tuple(float(v) for v in configured)
    return (1.0, 1.0, 1.0) if scene_has_alpha else (0.0, 0.0, 0.0)


__all__ = ["Views", "downscale_views", "recomposite", "resolve_background", "views_of"]
