"""The training views of a run: a split's cameras, images (torch tensors, composited over the
load background), times and alphas (`Views`), at another resolution (`downscale_views`, the
resolution warm-up of docs/training.md), the background arithmetic of training over another
colour (`recomposite`, `resolve_background`), and views rendered with some Gaussians made
transparent (`transparent`)."""

from __future__ import annotations

import contextlib
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


def shown_psnr(res, target: torch.Tensor, alpha, background, shown) -> float:
    """PSNR of a render `res` (rgb, alpha) made over `background` against its `target` (alpha:
    the target's, or None) composited there, both seen over the background `shown` (a training
    step's logged PSNR is against the evaluation background, whatever the step trained over)."""
    from nehad.losses import psnr

    if alpha is not None and background != shown:
        target = recomposite(target, alpha, background, shown)
    return psnr(recomposite(res.rgb.detach(), res.alpha.detach()[:, :, None], background, shown),
                target)


def resolve_background(configured, scene_has_alpha: bool) -> tuple[float, float, float]:
    """The colour a run renders over: data.background when set, else white for scenes with
    alpha (the D-NeRF convention) and black for the others."""
    if configured is not None:
        return tuple(float(v) for v in configured)
    return (1.0, 1.0, 1.0) if scene_has_alpha else (0.0, 0.0, 0.0)


def render_views(model, deforms: bool, indices, views, degree: int, background, clouds=None):
    """(cameras, targets, alphas or None, renders) of the views `indices`, each rendered at its
    own time (the canonical Gaussians in a static stage) over `background`; the Gaussians each
    was drawn from are appended to `clouds` when given."""
    from nehad.model import cloud_at
    from nehad.runtime.raster import render

    times = np.asarray(views.times, np.float64)
    canonical = None if deforms else cloud_at(model, None, degree)
    cams, targets, alphas, drawn = [], [], [], []
    for k in indices:
        cloud = canonical if canonical is not None else cloud_at(model, times[k], degree)
        cams.append(views.cameras[k])
        drawn.append(render(cloud, views.cameras[k], background))
        if clouds is not None:
            clouds.append(cloud)
        targets.append(views.images[k].numpy())
        a = views.alphas[k]
        alphas.append(None if a is None else a.numpy()[:, :, 0])
    return cams, targets, alphas, drawn


@contextlib.contextmanager
def transparent(g, rows):
    """The Gaussians `rows` of `g` transparent inside the block, their opacities restored after."""
    rows = torch.as_tensor(np.asarray(rows, np.int64))
    with torch.no_grad():
        kept = g.opacity_logits[rows].clone()
        g.opacity_logits[rows] = -30.0
    try:
        yield
    finally:
        with torch.no_grad():
            g.opacity_logits[rows] = kept


__all__ = ["Views", "downscale_views", "recomposite", "render_views", "resolve_background",
           "transparent", "views_of"]
