"""The hex-plane's three regularisers (docs/design.md section 5: the spatial planes' total
variation, the space-time planes' second differences along t and their mean |1 - p|) as ONE
autograd Function over all the planes, whose gradients are views of one array laid out as the
planes' own buffer (`nehad.field.hexplane.HexPlane` keeps its planes as channel-last views of
one flat array, one after the other).

Autograd keeps a gradient that arrives first and is laid out as its parameter as that
parameter's `.grad` (and adds the lookup's to it in place), so the planes' gradients stay views
of one array through the backward and the optimizer's flat step reads them without a copy
(`nehad.optim.TrainingAdam`, docs/performance.md). Per plane, the values and the gradients are
those of `hexplane_kernel.plane_tv` and `hexplane_kernel.time_regularisers` (the same Numba
passes), summed over the planes in the same order, so training computes the same bits
(tests/test_hexplane_kernel.py).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from nehad.field.hexplane_kernel import _plane_tv, _rows_of, _time_regularisers


def _ordered_sum(values: list) -> torch.Tensor:
    """sum(values) as Python's sum gives it over float32 tensors (0 + v1 + v2 + ...)."""
    total = 0
    for v in values:
        total = total + v
    return total


class PlaneRegularisers(torch.autograd.Function):
    """(total variation of the spatial planes, second differences along t and mean |1 - p| of
    the space-time planes), each summed over its planes; `is_time[k]` says which kind plane k
    is."""

    @staticmethod
    def forward(ctx, is_time, *planes):
        offsets = np.concatenate([[0], np.cumsum([p.numel() for p in planes])]).astype(np.int64)
        grad = np.empty(int(offsets[-1]), np.float32)  # every plane's, in the planes' layout
        l1_grads, views, sums = {}, [], ([], [], [])
        for k, (plane, timed) in enumerate(zip(planes, is_time)):
            _, c, h, w = plane.shape
            flat, rows, height, width, lag, as_plane = _rows_of(plane)
            part = grad[offsets[k]:offsets[k + 1]]
            rows_sums = np.empty((rows, 2), np.float64)
            if timed:
                l1_grads[k] = np.empty_like(flat)
                second, l1 = _time_regularisers(flat, rows, height, width, c * max(h - 2, 0) * w,
                                                c * h * w, part, l1_grads[k], rows_sums)
                sums[1].append(plane.new_tensor(second))
                sums[2].append(plane.new_tensor(l1))
            else:
                sums[0].append(plane.new_tensor(_plane_tv(flat, rows, height, width, lag,
                                                          c * (h - 1) * w, c * h * (w - 1),
                                                          part, rows_sums)))
            views.append((as_plane(part), None if not timed else as_plane(l1_grads[k])))
        ctx.views = views
        return tuple(_ordered_sum(s) for s in sums)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_tv, grad_second, grad_l1):
        views, ctx.views = ctx.views, None  # the forward's own arrays, scaled in place
        out = []
        for first, l1 in views:
            if l1 is None:  # as PlaneTV's backward
                out.append(first.mul_(grad_tv))
            else:  # as TimeRegularisers' backward
                out.append(first.mul_(grad_second).add_(l1.mul_(grad_l1)))
        return (None, *out)


def plane_regularisers(planes, is_time) -> tuple:
    """`PlaneRegularisers` of `planes` (1, C, H, W) float32, `is_time` one bool per plane."""
    return PlaneRegularisers.apply(tuple(bool(t) for t in is_time), *planes)


__all__ = ["PlaneRegularisers", "plane_regularisers"]
