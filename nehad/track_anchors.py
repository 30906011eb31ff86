"""A track's path taught to the deformation field (`carve.anchor_weight`, off by default;
docs/training.md, "Track anchors").

The tracks passes (nehad.tracks) draw an object that no Gaussian of the field draws with chains
of Gaussians that each live about one frame step around their own time. Across a gap of the
split (the test and validation times after a block's last training time) only the tails of the
chain's last members draw it, so an object drawn by chains alone fades there: on the stress
suite's occluder the sphere scored +8.4 dB over blank at a block's last training time and
+5.5 three steps later, with the chains' Gaussians made transparent +0.0 at every offset
(`bench/gap_probe.py`, docs/results.md, 2026-11-29), while objects the field carries (the
crossing spheres) keep their score across the gap.

An anchor is a virtual point at the track's place at the canonical time c (the nearest time of
its span), mu = x(c), and the loss asks the field to carry it along the track:

    L_anchor = w * mean_j |mu_j + d(mu_j, t_j) - x(t_j)|^2 / extent^2

over `samples` (anchor, time) pairs a step, the times those of the track's frame steps. The
field's cells around mu then move what sits there along the path, and Gaussians that live at
every time are added at mu, meant to draw the object there as the field's (not a chain's).
Only tracks with at least `min_blobs` blobs are anchored (a long path, not junk).
The Gaussians of an anchor are added at the pass after the one that found its track (`ready`):
added at once, they sit at mu at every time before the field has learnt the path, the views
of the other times make them transparent and densification prunes them (measured on the
occluder, docs/results.md, 2026-11-29). Measured there: the field learns the paths, but the
added Gaussians do not survive either way, and the scene loses 0.9-2.1 dB; off by default.
"""

from __future__ import annotations

import numpy as np
import torch


class TrackAnchors:
    """The anchors of a run and their loss (module docstring)."""

    def __init__(self, weight: float = 0.0, samples: int = 512, min_blobs: int = 12,
                 seed: int = 0, canonical_time: float = 0.5):
        self.weight, self.samples, self.min_blobs = float(weight), int(samples), int(min_blobs)
        self.seed, self.canonical_time = int(seed), float(canonical_time)
        self.points = np.zeros((0, 3))  # (R, 3): each row's anchor mu
        self.times = np.zeros(0)  # (R,)
        self.targets = np.zeros((0, 3))  # (R, 3): the track's point at the row's time
        self.sizes = np.zeros(0)  # (R,): the object's radius, the virtual point's scale
        self.waiting = np.zeros((0, 7))  # anchors without Gaussians yet: mu, rgb, radius

    @classmethod
    def of(cls, carve_cfg, seed: int, canonical_time: float) -> "TrackAnchors":
        return cls(carve_cfg.anchor_weight, carve_cfg.anchor_samples,
                   carve_cfg.anchor_min_blobs, seed, canonical_time)

    @property
    def on(self) -> bool:
        return self.weight > 0.0

    def add(self, track, spacing: float, size: float) -> np.ndarray | None:
        """Anchor `track` (nehad.tracks.Track) with rows one frame `spacing` apart over its
        span; returns its mu (3,), or None when the track is too short to anchor."""
        if not self.on or len(track.blobs) < self.min_blobs:
            return None
        taus = np.arange(track.times[0], track.times[-1] + 1e-9, spacing)
        pts, _ = track.at(taus)
        ref = float(np.clip(self.canonical_time, track.times[0], track.times[-1]))
        mu = track.at(np.array([ref]))[0][0]
        n = len(taus)
        self.points = np.concatenate([self.points, np.repeat(mu[None], n, 0)])
        self.times = np.concatenate([self.times, taus])
        self.targets = np.concatenate([self.targets, pts])
        self.sizes = np.concatenate([self.sizes, np.full(n, size)])
        self.waiting = np.concatenate([self.waiting, np.concatenate(
            [mu, np.asarray(track.colour(), np.float64).reshape(3), [size]])[None]])
        return mu

    def ready(self) -> np.ndarray:
        """The anchors of the earlier passes that have no Gaussians yet, (A, 7) rows of mu,
        rgb, radius; they count as having them from now on. Call before `add`."""
        rows, self.waiting = self.waiting, np.zeros((0, 7))
        return rows

    def loss(self, model, step: int):
        """L_anchor of `step` (0.0 without anchors)."""
        if not self.on or len(self.times) == 0:
            return 0.0
        rng = np.random.default_rng([self.seed, int(step), 13])
        rows = rng.choice(len(self.times), min(self.samples, len(self.times)), replace=False)
        field = model.field
        dtype = model.gaussians.means.dtype
        mu = torch.as_tensor(self.points[rows], dtype=dtype)
        log_scales = torch.log(torch.as_tensor(self.sizes[rows], dtype=dtype))[:, None].repeat(1, 3)
        quats = torch.zeros((len(rows), 4), dtype=dtype)
        quats[:, 0] = 1.0
        t = torch.as_tensor(self.times[rows], dtype=dtype)[:, None]
        t_eq = torch.full((len(rows), 1), self.canonical_time, dtype=dtype)
        out = field(mu, log_scales, quats, t, mu, t_eq)
        miss = out.means - torch.as_tensor(self.targets[rows], dtype=dtype)
        extent = float(field.extent)
        return self.weight * (miss * miss).sum(dim=1).mean() / (extent * extent)

    def state_dict(self) -> dict:
        return {"points": torch.as_tensor(self.points), "times": torch.as_tensor(self.times),
                "targets": torch.as_tensor(self.targets), "sizes": torch.as_tensor(self.sizes),
                "waiting": torch.as_tensor(self.waiting)}

    def load_state_dict(self, state: dict | None) -> None:
        if not state:
            return
        self.points = state["points"].numpy().reshape(-1, 3)
        self.times = state["times"].numpy().reshape(-1)
        self.targets = state["targets"].numpy().reshape(-1, 3)
        self.sizes = state["sizes"].numpy().reshape(-1)
        self.waiting = state["waiting"].numpy().reshape(-1, 7)


__all__ = ["TrackAnchors"]
