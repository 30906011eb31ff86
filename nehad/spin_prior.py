"""A spinning body's turn taught to the deformation field (`loss.spin_weight`, off by default;
docs/training.md, "Objects that spin").

Trained from images the field fits each training view of a spinning textured body from its
own camera and does not turn it: the stress suite's striped box turns at 12.57 rad per unit of
time and the field's Gaussians on it at 3.0-3.6, so across a block's held-out gap its stripes
slide over its faces and scramble (docs/results.md, 2026-11-29, "The striped box's Gaussians
do not turn with it"). Given the motion, the same field carries the box to 2% of its width
(`bench/motion_fit.py`): what the fit lacks is anything that makes turning cheaper than
refitting each view.

The carried-objects stage already measures a body's turn from its blobs' shapes
(`nehad.spin_tracks.spinning_tracks`, `nehad.spin.estimate_spin`). With this prior the
deforming stage's tracks pass runs that search too (on the model of the moment, every
training view) and keeps each spinning body's path c(t) over the span its track saw, its
angular velocity w and its half length r. From then on, at a step whose view time t lies in a
body's span, up to `samples` of the field's Gaussians (not the chains) whose place at t is
within r of c(t) are also deformed to t' = t + h (h = `SPIN_STEPS` frame spacings, back
where that leaves the span), and

    L_spin = w_s * mean_i |(x_i(t') - xbar(t')) - R(w (t' - t)) (x_i(t) - xbar(t))|^2 / r^2

asks their spread about their own mean to turn as the body does: the mean itself, where the
path's blob centroids wander, is left to the images. The selection is by place and has no
gradient; both times do.
"""

from __future__ import annotations

import numpy as np
import torch

from nehad.spin import rotations

#: The second time of a pair is this many frame spacings after the view's (before it at the
#: span's end): across a block's held-out gap (7 spacings) is where the turn is lost.
SPIN_STEPS = 2

#: Fewer selected Gaussians than this at a step: no term for that body (a mean and a spread
#: need a few points).
MIN_POINTS = 8


class SpinPrior:
    """The spinning bodies of a run and their loss (module docstring)."""

    def __init__(self, weight: float = 0.0, samples: int = 256, seed: int = 0):
        self.weight, self.samples, self.seed = float(weight), int(samples), int(seed)
        self.spacing = 0.0
        self.bodies: list[dict] = []  # each: times (k,), points (k, 3), omega (3,), radius

    @classmethod
    def of(cls, loss_cfg, seed: int) -> "SpinPrior":
        return cls(loss_cfg.spin_weight, loss_cfg.spin_samples, seed)

    @property
    def on(self) -> bool:
        return self.weight > 0.0

    def find(self, model, views, degree: int, background, carve_cfg, spacing: float) -> int:
        """Search the training `views` for spinning bodies (`nehad.spin_tracks`) and keep them
        (replacing those of an earlier search); how many."""
        from nehad.spin_tracks import moving_rows, smooth_path, spinning_tracks

        tracks, spins, _ = spinning_tracks(model, views, degree, background, carve_cfg,
                                           spacing, moving_rows(model))
        self.spacing, self.bodies = float(spacing), []
        for track, spin in zip(tracks, spins):
            times = np.arange(track.times[0], track.times[-1] + 0.5 * spacing, spacing)
            points, _ = smooth_path(track, times)
            half = float(np.sqrt(3.0 * max(np.linalg.eigvalsh(spin.spread)[-1], 0.0)))
            self.bodies.append({"times": times, "points": points,
                                "omega": np.asarray(spin.omega, np.float64), "radius": half})
        return len(self.bodies)

    def loss(self, model, deformed_means: torch.Tensor, t: float, step: int):
        """L_spin for the step's view at time `t`, `deformed_means` (N, 3) its field's places
        at t (0.0 when no body's span holds t)."""
        total = 0.0
        if not self.on or not self.bodies:
            return total
        mortal = model.gaussians.mortal().numpy()
        for k, body in enumerate(self.bodies):
            rows, t2 = self._pick(body, deformed_means, mortal, t, step, k)
            if rows is None:
                continue
            x0 = deformed_means[torch.as_tensor(rows)]
            x1 = model.means_at(t2, torch.as_tensor(rows))
            turn = torch.as_tensor(rotations(body["omega"] * (t2 - t)), dtype=x0.dtype)
            d0, d1 = x0 - x0.mean(0), x1 - x1.mean(0)
            err = ((d1 - d0 @ turn.T) ** 2).sum(1).mean() / body["radius"] ** 2
            total = total + self.weight * err
        return total

    def _pick(self, body: dict, deformed_means, mortal: np.ndarray, t: float, step: int,
              k: int):
        """(the rows of field Gaussians within the body's half length of its path at t, at
        most `samples`, drawn by a generator of the run's seed and the step; the pair's second
        time), or (None, None)."""
        times = body["times"]
        if not times[0] <= t <= times[-1] or self.spacing <= 0.0:
            return None, None
        t2 = t + SPIN_STEPS * self.spacing
        if t2 > times[-1]:
            t2 = t - SPIN_STEPS * self.spacing
        if t2 < times[0]:
            return None, None
        centre = np.array([np.interp(t, times, body["points"][:, j]) for j in range(3)])
        at = deformed_means.detach().numpy()
        near = np.linalg.norm(at - centre, axis=1) <= body["radius"]
        rows = np.flatnonzero(near & ~mortal)
        if len(rows) < MIN_POINTS:
            return None, None
        if len(rows) > self.samples:
            rng = np.random.default_rng([self.seed, step, 11, k])
            rows = np.sort(rng.choice(rows, self.samples, replace=False))
        return rows, float(t2)

    def state_dict(self) -> dict:
        return {"spacing": self.spacing,
                "bodies": [{key: (torch.as_tensor(v) if key != "radius" else v)
                            for key, v in b.items()} for b in self.bodies]}

    def load_state_dict(self, state: dict | None) -> None:
        if not state:
            return
        self.spacing = float(state["spacing"])
        self.bodies = [{key: (v.numpy() if torch.is_tensor(v) else float(v))
                        for key, v in b.items()} for b in state["bodies"]]


__all__ = ["SPIN_STEPS", "SpinPrior"]
