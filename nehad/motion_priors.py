"""The priors that a deforming step adds to its loss (docs/training.md): on the motion, each
Gaussian keeps its neighbours' distances (`nehad.isometry`), its path bends little
(`nehad.acceleration`), its size changes slowly (`nehad.scale_rate`); on the appearance, a
Gaussian of the background's colour pays for its opacity (`nehad.erasers`). Each is off at
weight 0, `LossConfig`'s default; the `cpu` preset turns on the slow-size prior
(`loss.scale_rate_weight=0.1`) and the erasers' (`loss.eraser_weight`)."""

from __future__ import annotations

from typing import NamedTuple

from nehad.acceleration import AccelerationPrior
from nehad.erasers import EraserPrior
from nehad.isometry import IsometryPrior
from nehad.scale_rate import ScaleRatePrior
from nehad.spin_prior import SpinPrior
from nehad.track_anchors import TrackAnchors


class MotionPriors(NamedTuple):
    isometry: IsometryPrior
    acceleration: AccelerationPrior
    scale_rate: ScaleRatePrior
    anchors: TrackAnchors  # the tracks' paths taught to the field (carve.anchor_weight)
    erasers: EraserPrior
    spins: SpinPrior  # spinning bodies' turns taught to the field (loss.spin_weight)

    @classmethod
    def of(cls, loss_cfg, seed: int, times, carve_cfg=None, canonical_time: float = 0.5,
           background=(1.0, 1.0, 1.0)) -> "MotionPriors":
        """The priors a `LossConfig` asks for, over the training views' `times` and a run's
        `background`, and the track anchors a `CarveConfig` asks for (none without one)."""
        anchors = (TrackAnchors() if carve_cfg is None
                   else TrackAnchors.of(carve_cfg, seed, canonical_time))
        return cls(IsometryPrior.of(loss_cfg), AccelerationPrior.of(loss_cfg, seed, times),
                   ScaleRatePrior.of(loss_cfg, seed, times), anchors,
                   EraserPrior.of(loss_cfg, background), SpinPrior.of(loss_cfg, seed))

    def gaussians_at(self, model, t: float, step: int, deform: bool):
        """(model.gaussians_at(t, deform)'s tuple, the field's output for the slow-size prior's
        samples or None): when the prior is on, its samples are deformed in the same field
        evaluation as the view (`NeHaDModel.gaussians_and_samples_at`)."""
        prior = self.scale_rate
        picked = prior.rows_and_times(len(model.gaussians), step, t) if deform else None
        if picked is None:
            return model.gaussians_at(t, deform=deform), None
        return model.gaussians_and_samples_at(t, *picked, with_view_rows=prior.pairs_with_view)

    def loss(self, model, deformed_means, t: float, step: int, sampled=None):
        """Their sum for the view at time `t` of `step`, `deformed_means` (N, 3) the step's
        deformed means at t, `sampled` what `gaussians_at` returned for the samples."""
        return (self.isometry.loss(model.gaussians, deformed_means, step)
                + self.acceleration.loss(model, deformed_means, t, step)
                + self.scale_rate.loss(model, step, sampled, t) + self.anchors.loss(model, step)
                + self.erasers.loss(model.gaussians)
                + self.spins.loss(model, deformed_means, t, step))

    def state_dict(self) -> dict:
        """What a checkpoint keeps of them: what the tracks passes found."""
        return {"anchors": self.anchors.state_dict(), "spins": self.spins.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.anchors.load_state_dict(state.get("anchors"))
        self.spins.load_state_dict(state.get("spins"))


__all__ = ["MotionPriors"]
