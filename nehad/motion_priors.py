"""The priors on the motion that a deforming step adds to its loss (docs/training.md): each
Gaussian keeps its neighbours' distances (`nehad.isometry`), its path bends little
(`nehad.acceleration`), its size changes slowly (`nehad.scale_rate`). Each is off at weight 0,
its default."""

from __future__ import annotations

from typing import NamedTuple

from nehad.acceleration import AccelerationPrior
from nehad.isometry import IsometryPrior
from nehad.scale_rate import ScaleRatePrior


class MotionPriors(NamedTuple):
    isometry: IsometryPrior
    acceleration: AccelerationPrior
    scale_rate: ScaleRatePrior

    @classmethod
    def of(cls, loss_cfg, seed: int, times) -> "MotionPriors":
        """The priors a `LossConfig` asks for, over the training views' `times`."""
        return cls(IsometryPrior.of(loss_cfg), AccelerationPrior.of(loss_cfg, seed, times),
                   ScaleRatePrior.of(loss_cfg, seed, times))

    def loss(self, model, deformed_means, t: float, step: int):
        """Their sum for the view at time `t` of `step`, `deformed_means` (N, 3) the step's
        deformed means at t."""
        return (self.isometry.loss(model.gaussians, deformed_means, step)
                + self.acceleration.loss(model, deformed_means, t, step)
                + self.scale_rate.loss(model, step))


__all__ = ["MotionPriors"]
