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
axis and step. The two times are 2 x `samples` rows of the field; in training they ride on
the view's own field evaluation (`rows_and_times`, `NeHaDModel.gaussians_and_samples_at`),
where a call of their own cost about 10 ms a step, mostly the field's fixed costs
(docs/performance.md).

With `times="view"` (`loss.scale_rate_times`) the pair is the step's view's time t and one
frame step before or after it (a fair coin from the same generator; the one that stays inside
the training times at their ends): the view's own rows at t are reused, so the prior adds one
field row per sample instead of two.
"""

from __future__ import annotations

import torch

from nehad.acceleration import time_step_and_span


class ScaleRatePrior:
    """The prior's loss for one step (module docstring)."""

    def __init__(self, weight: float, samples: int, seed: int = 0, times: str = "uniform"):
        self.weight, self.samples, self.seed = float(weight), int(samples), int(seed)
        self.times = times  # "uniform": c anywhere, two rows per sample; "view": the view's t
        self.step_h = None  # the training views' time step (set from their times)
        self.span = None  # (first, last) training time

    @classmethod
    def of(cls, loss_cfg, seed: int, times) -> "ScaleRatePrior":
        """The prior a `LossConfig` asks for (its scale_rate_* knobs), over the training views'
        `times`."""
        prior = cls(loss_cfg.scale_rate_weight, loss_cfg.scale_rate_samples, seed,
                    loss_cfg.scale_rate_times)
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

    @property
    def pairs_with_view(self) -> bool:
        """Whether the first time of each pair is the view's, its rows the view's own."""
        return self.times == "view"

    def neighbour_time(self, t: float, step: int) -> float:
        """With `times="view"`: the time one frame step from the view's t that `step` pairs it
        with (after or before it by a fair coin; the one inside the training times at their
        ends)."""
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + int(step) + 11)
        later = bool(torch.rand((), generator=gen, dtype=torch.float64) < 0.5)
        h, (first, last) = self.step_h, self.span
        if float(t) + h > last + 1e-9:
            later = False
        elif float(t) - h < first - 1e-9:
            later = True
        return float(t) + h if later else float(t) - h

    def rows_and_times(self, n: int, step: int, t: float | None = None):
        """(rows, times): the rows the field must deform for `step`'s term among n Gaussians
        and their times: with `times="uniform"` the Gaussians twice, at c and then at c + h;
        with `times="view"` (the view's time `t` required) once, at the neighbour time, the
        view's own rows at t being the pair's first half. None when the term is off, without a
        time step, when the training times span under one step, or without Gaussians."""
        h = self.step_h
        if self.weight <= 0.0 or h is None or self.span[1] - self.span[0] < h or n == 0:
            return None
        rows, c = self.draw(n, step)
        m = len(rows)
        if self.pairs_with_view:
            if t is None:
                raise ValueError("the slow-size prior pairs with the view's time: give t")
            return rows, torch.full((m,), self.neighbour_time(t, step), dtype=torch.float64)
        times = torch.cat([torch.full((m,), c, dtype=torch.float64),
                           torch.full((m,), c + h, dtype=torch.float64)])
        return torch.cat([rows, rows]), times

    def loss(self, model, step: int, deformed=None, t: float | None = None):
        """L_rate of `step` (0.0 when `rows_and_times` is None). `deformed`: the field's output
        for the pairs' rows, the first time's rows then the second's, when the caller evaluated
        them (no second draw then: `NeHaDModel.gaussians_and_samples_at`); else the prior draws
        and calls the field itself (at the view's time `t` and its neighbour with
        `times="view"`)."""
        if deformed is None:
            g = model.gaussians
            picked = self.rows_and_times(int(g.means.shape[0]), step, t)
            if picked is None:
                return 0.0
            rows, times = picked
            if self.pairs_with_view:
                rows = torch.cat([rows, rows])
                times = torch.cat([torch.full_like(times, float(t)), times])
            deformed = model.field(g.means[rows], g.log_scales[rows], g.quats[rows],
                                   times.to(g.means.dtype)[:, None], g.mu_eq[rows], g.t_eq[rows])
        m = deformed.log_scales.shape[0] // 2  # the rows at one time, then the same at the other
        change = deformed.log_scales[m:] - deformed.log_scales[:m]
        return self.weight * (change * change).sum(dim=1).mean()


__all__ = ["ScaleRatePrior"]
