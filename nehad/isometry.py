"""A local isometry prior on the deformation (`loss.isometry_weight`, docs/training.md "Objects
that break apart"): neighbouring Gaussians keep their distance at every time. Off by default:
held to the canonical distances it did not help (docs/results.md, 2026-11-27).

The photometric loss sees each time through one or two views. Between them the field is free to
move the Gaussians of one object apart along the views' rays, and a spinning or occluded object
is drawn as scattered fragments at the held-out times. Dynamic 3D Gaussians (Luiten et al.,
3DV 2024) hold each Gaussian to its nearest neighbours; this module keeps the rotation-free part
of that, the isometry term:

    L_iso = w * sum_ij a_ij | D_ij(t) - m_i(t) d_ij | / (s * sum_ij a_ij)

over each Gaussian i's K nearest canonical neighbours j, with d_ij their canonical distance,
D_ij(t) = |mu_i(t) - mu_j(t)|, a_ij = exp(-d_ij^2 / (2 s^2)), s the (lower) median d_ij (the scene's
own neighbour spacing, so the weight means the same at any scale) and m_i(t) the scale that
fits i's neighbourhood best, sum_j a_ij D_ij d_ij / sum_j a_ij d_ij^2 (`local_scale`; else 1).
It turns and travels with a rigid object, and with `local_scale` it grows with one (the stress
suite's `scaling`), at no cost; what it resists is tearing and sliding: on trained models
without it, 59-65% of the opaque neighbours at one time are more than a neighbour spacing closer
or further apart 0.1 later, on scenes whose every object is rigid (docs/training.md).
Gaussians with a finite life (the tracks' chains) take no part: they live at one time only.
The pairs are found again whenever the set of Gaussians changes (densification replaces the
means' parameter) and at every step that is a multiple of `refresh`, which must divide the
checkpoint interval (the config checks it): a run resumed from a checkpoint then searches where
the uninterrupted run does and computes the same (tests/test_fingerprint.py); the prior keeps
no other state.
With `reference="time"` the pairs and d_ij are the deformed Gaussians' at the step that found
them, instead of the canonical ones': the other times are held to a shape the scene had.
"""

from __future__ import annotations

import torch

from nehad.neighbours import nearest_neighbours

#: Steps between two searches for neighbours while the set of Gaussians is unchanged.
REFRESH = 100


class IsometryPrior:
    """The pairs of the prior (module docstring) and its loss at one time."""

    def __init__(self, weight: float, neighbours: int, local_scale: bool = True,
                 reference: str = "canonical", refresh: int = REFRESH):
        self.weight, self.neighbours = float(weight), int(neighbours)
        self.local_scale, self.reference, self.refresh = bool(local_scale), reference, refresh
        self._means_param = None
        self._found_at = None
        self.pairs = None  # (i, j, canonical distance, weight / (s sum of weights))

    @classmethod
    def of(cls, loss_cfg) -> "IsometryPrior":
        """The prior a `LossConfig` asks for (its isometry_* knobs)."""
        return cls(loss_cfg.isometry_weight, loss_cfg.isometry_neighbours,
                   loss_cfg.isometry_local_scale, loss_cfg.isometry_reference,
                   loss_cfg.isometry_refresh)

    def _find(self, gaussians, step: int, deformed_means: torch.Tensor) -> None:
        self._means_param, self._found_at = gaussians.means, step
        with torch.no_grad():
            rows = torch.nonzero(gaussians.life_rate.reshape(-1) == 0).reshape(-1)
            ref = gaussians.means if self.reference == "canonical" else deformed_means
            # too few to pair, or a diverged step (the trainer stops on its non-finite loss)
            if len(rows) <= self.neighbours or not torch.isfinite(ref).all():
                self.pairs = None
                return
            j, d = nearest_neighbours(ref.detach()[rows].numpy(), self.neighbours)
            i = rows[:, None].expand(-1, j.shape[1]).reshape(-1)
            j = rows[torch.from_numpy(j.reshape(-1))]
            d = torch.from_numpy(d.reshape(-1)).to(gaussians.means.dtype)
            s = torch.clamp(d.median(), min=1e-12)
            self.spacing = float(s)
            a = torch.exp(-0.5 * torch.square(d / s))
            self.pairs = (i, j, d, a / (s * a.sum()))

    def loss(self, gaussians, deformed_means: torch.Tensor, step: int):
        """L_iso of the deformed means (N, 3) at one time; 0.0 when off or without pairs."""
        if self.weight <= 0.0:
            return 0.0
        if gaussians.means is not self._means_param or step % self.refresh == 0:
            self._find(gaussians, step, deformed_means)
        if self.pairs is None:
            return 0.0
        i, j, d, a = self.pairs
        # a floor under the distance: clones sit on their parent (d = 0), where |x| has no slope
        tiny = 1e-6 * float(self.spacing)
        # index_select, not x[i]: its backward (index_add_) sums in one order whatever the
        # number of threads, where advanced indexing's backward does not
        diff = (torch.index_select(deformed_means, 0, i)
                - torch.index_select(deformed_means, 0, j))
        now = torch.sqrt(torch.sum(diff * diff, dim=1) + tiny * tiny)
        if self.local_scale:  # pairs come in rows of K per Gaussian i (`_find`)
            k = self.neighbours  # _find pairs only more rows than K: none clipped
            ad = (a * d).reshape(-1, k)
            fit = torch.sum(ad * d.reshape(-1, k), 1)
            m = torch.where(fit > 0, torch.sum(ad * now.reshape(-1, k), 1)
                            / torch.clamp(fit, min=tiny * tiny), torch.ones_like(fit))
            d = (d.reshape(-1, k) * m[:, None]).reshape(-1)
        return self.weight * torch.sum(a * torch.abs(now - d))


__all__ = ["IsometryPrior", "REFRESH"]
