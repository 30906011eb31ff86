"""A prior against erasers (`loss.eraser_weight`, docs/training.md "Erasers"): a Gaussian of
the background's colour pays for its opacity.

Over a plain background such a Gaussian is invisible wherever a view sees the background (or a
floor of its colour) behind it, so the photometric loss lets the model use it as an eraser:
on the stress occluder, clusters of 10-30 thin white Gaussians trim the soft edges of the wall
as ONE camera of the rig sees them (90-99% of what they are worth falls on that camera). From
every other camera they stand in free space, and an object that passes behind them is cut
(the occluded sphere on seeds 3 and 4: +6.5 dB over blank in its worst quarter, +8.9 with the
two clusters in front of it hidden; docs/results.md, 2026-11-30). Neither the training nor
the validation views tell a harmful eraser from a useful one afterwards, so the prior works
in training:

    L_eraser = w * sum_i o_i exp(-|c_i - b|^2 / (2 WIDTH^2))

over the Gaussians with an infinite life (the tracks' chains and the carried objects draw one
time each and take no part), o_i the opacity, c_i the colour of the SH degree-0 term, b the
background; the colour's weight is held, so the prior lowers an eraser's opacity and does not
recolour it. A Gaussian WIDTH off the background in each channel pays exp(-1.5) = 0.22 of it,
one 0.15 off nothing measurable. Since each term is one Gaussian's, w is the pull on one
opacity, the same at any Gaussian count.
"""

from __future__ import annotations

import torch

from nehad.runtime.gaussians import SH_C0

#: How near the background colour (per channel, as a Gaussian's standard deviation) a
#: Gaussian must be to pay.
WIDTH = 0.05


class EraserPrior:
    """The prior's loss for one step (module docstring); weight 0 is off."""

    def __init__(self, weight: float, background=(1.0, 1.0, 1.0)):
        self.weight = float(weight)
        self.background = torch.tensor([float(v) for v in background], dtype=torch.float32)

    @classmethod
    def of(cls, loss_cfg, background) -> "EraserPrior":
        return cls(loss_cfg.eraser_weight, background)

    def loss(self, gaussians):
        """w times the background-coloured opacity of the immortal Gaussians (a 0-d tensor, or
        0.0 when off or when none are left)."""
        if self.weight <= 0.0 or len(gaussians) == 0:
            return 0.0
        with torch.no_grad():
            colour = gaussians.sh_dc[:, 0, :] * SH_C0 + 0.5
            near = torch.exp(-((colour - self.background) ** 2).sum(1) / (2.0 * WIDTH ** 2))
            near = near * (~gaussians.mortal()).float()
        opacity = torch.sigmoid(gaussians.opacity_logits.reshape(-1))
        return self.weight * (near * opacity).sum()


__all__ = ["EraserPrior", "WIDTH"]
