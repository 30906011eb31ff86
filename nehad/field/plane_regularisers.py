"""The hex-plane's three regularisers (docs/design.md section 5: the spatial planes' total
variation, the space-time planes' second differences along t and their mean |1 - p|) as ONE
autograd Function over all the planes, with one gradient array laid out as the planes' own
buffer (`nehad.field.hexplane.HexPlane` keeps its planes as channel-last views of one flat
array, one after the other): one autograd node and one allocation a step where there were
twelve of each (docs/performance.md). Autograd adds these gradients into the planes' `.grad`,
which `nehad.optim.TrainingAdam.zero_grad` makes views of one array; in a training step
(`HexPlane.adding_gradients_in_place`) the backward adds them there itself, scaling them on
the way, and returns none. Per plane, the values and
the gradients are those of `hexplane_kernel.PlaneTV` and `hexplane_kernel.TimeRegularisers`
(the same passes, `tv_pass` and `time_pass`), summed over the planes in the same order as
`HexPlane.plane_smoothness` and `HexPlane.time_terms`, so training computes the same bits
(tests/test_hexplane_kernel.py).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from nehad.field.hexplane_kernel import time_pass, tv_pass


class PlaneRegularisers(torch.autograd.Function):
    """(total variation of the spatial planes, second differences along t and mean |1 - p| of
    the space-time planes), each summed over its planes; `is_time[k]` says which kind plane k
    is. With `into_grad`, a plane that has a `.grad` at the backward gets its gradient added
    into it there, scaled in the same pass, and none is returned for it (as the lookup's,
    `nehad.field.hexplane.HexPlane.adding_gradients_in_place`)."""

    @staticmethod
    def forward(ctx, is_time, into_grad, *planes):
        offsets = np.concatenate([[0], np.cumsum([p.numel() for p in planes])]).astype(np.int64)
        grad = np.empty(int(offsets[-1]), np.float32)  # every plane's, in the planes' layout
        l1_grads, views, sums = {}, [], ([], [], [])
        for k, (plane, timed) in enumerate(zip(planes, is_time)):
            part = grad[offsets[k]:offsets[k + 1]]
            if timed:
                l1_grads[k] = np.empty(plane.numel(), np.float32)
                second, l1, as_plane = time_pass(plane, part, l1_grads[k])
                sums[1].append(plane.new_tensor(second))
                sums[2].append(plane.new_tensor(l1))
            else:
                value, as_plane = tv_pass(plane, part)
                sums[0].append(plane.new_tensor(value))
            views.append((as_plane(part), None if not timed else as_plane(l1_grads[k])))
        ctx.views = views
        ctx.planes = planes if into_grad else None
        return tuple(sum(s) for s in sums)  # Python's sum, in order, as HexPlane's

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_tv, grad_second, grad_l1):
        views, ctx.views = ctx.views, None  # the forward's own arrays, scaled in place
        held = ctx.planes or [None] * len(views)
        out = []
        for (first, l1), plane, wanted in zip(views, held, ctx.needs_input_grad[2:]):
            grad = None if plane is None or not wanted else plane.grad
            if grad is not None:  # added into the plane's .grad, scaled on the way
                grad.add_(first, alpha=float(grad_tv if l1 is None else grad_second))
                if l1 is not None:
                    grad.add_(l1, alpha=float(grad_l1))
                out.append(None)
            elif l1 is None:  # as PlaneTV's backward
                out.append(first.mul_(grad_tv))
            else:  # as TimeRegularisers' backward
                out.append(first.mul_(grad_second).add_(l1.mul_(grad_l1)))
        return (None, None, *out)


def plane_regularisers(planes, is_time, into_grad: bool = False) -> tuple:
    """`PlaneRegularisers` of `planes` (1, C, H, W) float32, `is_time` one bool per plane; with
    `into_grad` the gradients are added into the planes' `.grad` where they have one (for a
    `.backward()` only)."""
    return PlaneRegularisers.apply(tuple(bool(t) for t in is_time), bool(into_grad), *planes)


__all__ = ["PlaneRegularisers", "plane_regularisers"]
