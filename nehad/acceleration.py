"""A smooth-motion prior on the deformation (`loss.acceleration_weight`, docs/training.md
"Paths that bend between the views"): each Gaussian's path bends little from one frame to the
next.

A MuJoCo split trains on 14 consecutive frames, then holds out 6 (3 test, 3 validation), so
every test frame lies inside a gap of 7 frame steps that no training view sees
(docs/results.md, 2026-11-27). What the field draws there is its interpolation between the
views on either side. On scene5 the Hamiltonian decoder's paths bend more from frame to frame
than the MLP decoder's (mean |x(t+h) - 2 x(t) + x(t-h)| 1.3-1.7x as large for the moving
Gaussians), and it scores 2.2-2.7 dB lower on the test views while fitting the training views
as well without the BED position mask. The prior asks for the straighter path (off by
default: +13.17 dB over blank on scene5 against the recipe's +12.10 to +12.62, but +9.20 on
scene8, whose turning rod's ends accelerate at every frame; docs/results.md, 2026-11-27):

    L_acc = w * mean_i |x_i(c + h) - 2 x_i(c) + x_i(c - h)| / extent

over `samples` Gaussians drawn afresh each step (the same draw for a run resumed from a
checkpoint: the generator is seeded by the run's seed and the step), x_i(t) the deformed mean
(with its drift) of Gaussian i at time t, h the training views' time step (the median spacing
of their distinct times), and c the view's time moved inside [t_min + h, t_max - h] of the
training times. The norm is not squared: a bounce, where the path does turn within a frame,
costs in proportion to the turn, not its square. With the view's time inside that range, x(c)
is the row of the deformed means the step renders, so the prior costs two field evaluations of
`samples` Gaussians. With `times="uniform"` (`loss.acceleration_times`) c is drawn uniformly in
that range instead (the same generator), so the prior also reaches the middle of the gaps
between the training views, at the cost of a third evaluation.
"""

from __future__ import annotations

import numpy as np
import torch


def time_step_and_span(times) -> tuple:
    """(h, (first, last)) of the training views' times: h the median spacing of the distinct
    ones (None with fewer than two), the span None without times."""
    t = np.unique(np.asarray(times, np.float64))
    steps = np.diff(t)
    steps = steps[steps > 0]
    return (float(np.median(steps)) if len(steps) else None,
            (float(t[0]), float(t[-1])) if len(t) else None)


class AccelerationPrior:
    """The prior's loss at the time of one view (module docstring)."""

    def __init__(self, weight: float, samples: int, seed: int = 0, times: str = "view"):
        self.weight, self.samples, self.seed = float(weight), int(samples), int(seed)
        self.times = times  # "view": centred on the step's view; "uniform": anywhere
        self.step_h = None  # the training views' time step (set from their times)
        self.span = None  # (first, last) training time

    @classmethod
    def of(cls, loss_cfg, seed: int, times) -> "AccelerationPrior":
        """The prior a `LossConfig` asks for (its acceleration_* knobs), over the training
        views' `times`."""
        prior = cls(loss_cfg.acceleration_weight, loss_cfg.acceleration_samples, seed,
                    loss_cfg.acceleration_times)
        prior.set_times(times)
        return prior

    def set_times(self, times) -> None:
        """The training views' times: h is the median spacing of the distinct ones."""
        self.step_h, self.span = time_step_and_span(times)

    def loss(self, model, deformed_means: torch.Tensor, t: float, step: int):
        """L_acc at the view's time `t`, `deformed_means` (N, 3) the step's deformed means at
        `t`; 0.0 when off, without a time step, or when the training times span under 2h."""
        h = self.step_h
        if self.weight <= 0.0 or h is None or self.span[1] - self.span[0] < 2 * h:
            return 0.0
        n = int(deformed_means.shape[0])
        if n == 0:
            return 0.0
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + int(step))
        rows = torch.randperm(n, generator=gen)[:self.samples]
        if self.times == "uniform":  # anywhere in the span, the gaps between the views too
            u = float(torch.rand((), generator=gen, dtype=torch.float64))
            centre = self.span[0] + h + u * (self.span[1] - self.span[0] - 2 * h)
        else:
            centre = min(max(float(t), self.span[0] + h), self.span[1] - h)
        x0 = (deformed_means[rows] if centre == float(t)
              else model.means_at(centre, rows))
        a = model.means_at(centre + h, rows) - 2.0 * x0 + model.means_at(centre - h, rows)
        size = torch.sqrt((a * a).sum(dim=1) + 1e-20)  # finite gradient at a = 0
        return self.weight * size.mean() / float(model.field.extent)


__all__ = ["AccelerationPrior", "time_step_and_span"]
