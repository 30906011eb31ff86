"""The shared CPU Gaussian rasterizer (docs/design.md section 6), as plain functions.

Stages, each small and testable on its own (the gsplat layout):
  1. `project_gaussians` (projection.py): 3D Gaussians + camera -> screen-space Gaussians.
  2. `bin_gaussians` (binning.py): screen-space Gaussians -> depth-sorted per-tile lists.
  3. `rasterize` / `rasterize_backward` (here, kernels in kernels.py): tile lists -> images, and
     image gradients -> gradients of the screen-space inputs.
`render` chains the three for the torch-free runtime; training calls all three through
`nehad.splat.rasterize` (the same Numba projection and its hand-written backward, wrapped for
autograd).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .binning import TileBins, bin_gaussians
from .heap import keep_freed_memory
from .kernels import backward_kernel, forward_kernel, interleaved_tiles, sum_entry_grads
from .projection import Projected, _f32, project_gaussians
from ..threads import frame_threads

keep_freed_memory()  # reuse frame buffers instead of new pages (heap.py; NEHAD_KEEP_HEAP=0: off)

__all__ = ["RasterOutput", "ScreenGradients", "TileBins", "Projected", "bin_gaussians",
           "project_gaussians", "rasterize", "rasterize_backward", "render"]


@dataclass
class RasterOutput:
    """rgb (H, W, 3), alpha (H, W) = 1 - T_final, depth (H, W); `final_t` and `stop` (each
    pixel's stopping index in its tile list) are kept for the backward pass."""

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    final_t: np.ndarray
    stop: np.ndarray
    bins: TileBins


@dataclass
class ScreenGradients:
    means2d: np.ndarray  # (N, 2)
    conics: np.ndarray  # (N, 3)
    colors: np.ndarray  # (N, 3)
    opacities: np.ndarray  # (N,)


def rasterize(means2d, conics, colors, opacities, depths, radii, width, height,
              background=(0.0, 0.0, 0.0), bins: TileBins | None = None) -> RasterOutput:
    """Draw screen-space Gaussians front to back in 16x16 tiles (forward pass)."""
    means2d, conics, colors, opacities, depths = (_f32(means2d), _f32(conics), _f32(colors),
                                                  _f32(opacities), _f32(depths))
    width, height = int(width), int(height)
    if bins is None:
        bins = bin_gaussians(means2d, conics, colors, opacities, depths,
                             np.ascontiguousarray(radii, np.int32), width, height)
    rgb = np.empty((height, width, 3), np.float32)
    final_t = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    stop = np.empty((height, width), np.int32)
    order = interleaved_tiles(bins.tiles_x, bins.tiles_y, numba.get_num_threads())
    forward_kernel(order, bins.tile_offsets, bins.gauss_ids, bins.packed, width, height,
                   _f32(background), rgb, final_t, depth, stop)
    return RasterOutput(rgb, 1.0 - final_t, depth, final_t, stop, bins)


def rasterize_backward(out: RasterOutput, grad_rgb, grad_alpha=None) -> ScreenGradients:
    """Gradients of a loss w.r.t. the screen-space inputs of the forward pass that produced
    `out` (its bins hold those inputs), given dL/d rgb and optionally dL/d alpha."""
    bins = out.bins
    h, w = out.final_t.shape
    if grad_alpha is None:
        grad_alpha = np.zeros((h, w), np.float32)
    n = bins.packed.shape[0]
    # zeros: the kernel skips the entries behind a tile's last stopping pixel (no gradient)
    entry = np.zeros((bins.gauss_ids.shape[0], 9), np.float32)
    order = interleaved_tiles(bins.tiles_x, bins.tiles_y, numba.get_num_threads())
    backward_kernel(order, bins.tile_offsets, bins.gauss_ids, bins.packed, w, h, out.rgb,
                    out.final_t, out.stop, _f32(grad_rgb), _f32(grad_alpha), entry)
    g = sum_entry_grads(bins.gauss_ids, entry, n)
    return ScreenGradients(g[:, 0:2], g[:, 2:5], g[:, 5:8], g[:, 8])


def render(cloud, camera, background=(0.0, 0.0, 0.0), sh_degree=None,
           adapt_threads: bool = True) -> RasterOutput:
    """Render a `GaussianCloud` through a `Camera` (projection, binning, rasterization).
    `adapt_threads`: first set numba's thread count to the cores the machine's load leaves free
    (runtime/threads.py); False keeps the count the caller set."""
    if adapt_threads:
        frame_threads()
    proj = project_gaussians(cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh,
                             camera, sh_degree)
    return rasterize(proj.means2d, proj.conics, proj.colors, proj.opacities, proj.depths,
                     proj.radii, camera.width, camera.height, background)
