"""A slow-size prior on the deformation (`loss.scale_rate_weight`, docs/training.md "Gaussians
that blink"): a Gaussian's size changes little from one frame to the next.

The field can draw what moves by letting different Gaussians appear and vanish over time, each
shrunk to nothing (its log-scale offset falling by several units) where it is not wanted, instead
of moving the same Gaussians along: on the stress suite's spinning rod the rod's Gaussians change
their largest axis 10.6x over time (median) and are under 0.3 of their largest size 69% of the
time; on scene8 (two rods) 3.9x, where scene7 changes 1.01x (docs/results.md, 2026-11-28). A
model that blinks fits each training view and draws fragments between them, where the test views
lie. The prior makes blinking cost:

    L_rate = w * mean_i |log s_i(c + h) - log s_i(c)|^2      (summed over the three axes)

over `samples` Gaussians drawn afresh each step and a time c drawn uniformly in [t_min, t_max - h]
of the training times (both from a generator seeded by the run's seed and the step, so a run
resumed from a checkpoint takes the same draws), h the training views' time step (the median
spacing of their distinct times). The square lets a size that changes steadily pass almost
free (the stress suite's `scaling` objects grow or shrink 4x over the whole time: 0.01 per
frame step, 1e-4 squared) while a Gaussian that blinks within a few frames pays about 0.5 per
axis and step. The two times are one field evaluation of 2 x `samples` rows.
"""

from __future__ import annotations

import torch

from nehad.acceleration import time_step_and_span


class ScaleRatePrior:
    """The prior's loss for one step (module docstring)."""

    def __init__(self, weight: float, samples: int, seed: int = 0):
        self.weight, self.samples, self.seed = float(weight), int(samples), int(seed)
        self.step_h = None  # the training views' time step (set from their times)
        self.span = None  # (first, last) training time

    @classmethod
    def of(cls, loss_cfg, seed: int, times) -> "ScaleRatePrior":
        """The prior a `LossConfig` asks for (its scale_rate_* knobs), over the training views'
        `times`."""
        prior = cls(loss_cfg.scale_rate_weight, loss_cfg.scale_rate_samples, seed)
        prior.set_times(times)
        return prior

    def set_times(self, times) -> None:
        """The training views' times: h is the median spacing of the distinct ones."""
        self.step_h, self.span = time_step_and_span(times)

    def draw(self, n: int, step: int) -> tuple[torch.Tensor, float]:
        """(rows, c): the Gaussians and the time of `step`'s term."""
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + int(step) + 7)
        rows = torch.randperm(n, generator=gen)[:self.samples]
        u = float(torch.rand((), generator=gen, dtype=torch.float64))
        return rows, self.span[0] + u * (self.span[1] - self.span[0] - self.step_h)

    def loss(self, model, step: int):
        """L_rate of `step`; 0.0 when off, without a time step, or when the training times span
        under one step."""
        h = self.step_h
        if self.weight <= 0.0 or h is None or self.span[1] - self.span[0] < h:
            return 0.0
        g = model.gaussians
        n = int(g.means.shape[0])
        if n == 0:
            return 0.0
        rows, c = self.draw(n, step)
        both = torch.cat([rows, rows])
        dtype = g.means.dtype
        t = torch.cat([torch.full((len(rows), 1), c, dtype=dtype),
                       torch.full((len(rows), 1), c + h, dtype=dtype)])
        out = model.field(g.means[both], g.log_scales[both], g.quats[both], t, g.mu_eq[both],
                          g.t_eq[both])
        change = out.log_scales[len(rows):] - out.log_scales[:len(rows)]
        return self.weight * (change * change).sum(dim=1).mean()


__all__ = ["ScaleRatePrior"]
