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

An anchor is a point at the track's place at the canonical time c (the nearest time of its
span), mu = x(c), and the loss asks the field to carry it along the track:

    L_anchor = w * mean_j |mu_j + o_j + d(mu_j + o_j, t_j) - x(t_j) - o_j|^2 / extent^2

over `samples` (anchor, time) pairs a step, the times those of the track's frame steps, and
o_j an offset uniform in a ball of `volume` object radii (`carve.anchor_volume`; 0: o = 0).
Trained at mu alone the field moves only the cells next to mu: Gaussians a radius away, where
the added ones end up, stayed still (measured on the occluder, docs/training.md). Only tracks
with at least `min_blobs` blobs are anchored (a long path, not junk). A track that continues
an anchored one (it overlaps that path's span and lies on it) extends that anchor's path: the
passes find one object in pieces, each the part that no earlier chain draws.
Gaussians that live at every time are added at mu at a later pass than the one that found the
track (`ready`), once the field has had time to learn the path, and, with `cover` > 0, only
once the path covers that share of the time range: elsewhere the field has not been told
where they are (measured: the added Gaussians followed the sphere inside their track's span
and were 0.9-1.1 away from it outside). With `carve.anchor_replace` the chain Gaussians on
the path are then removed (`near_path`), so that the field's Gaussians draw the object (with
the chains there, the added ones were made transparent and pruned). Measured on the stress
suite's occluder (docs/results.md, 2026-11-29): the field then draws the sphere at every time,
across the gaps as well as inside the blocks, but less sharply than the chains and at a cost
to the wall; off by default.
"""

from __future__ import annotations

import numpy as np
import torch


class TrackAnchors:
    """The anchors of a run and their loss (module docstring)."""

    def __init__(self, weight: float = 0.0, samples: int = 512, min_blobs: int = 12,
                 seed: int = 0, canonical_time: float = 0.5, volume: float = 0.0,
                 release: bool = False):
        self.weight, self.samples, self.min_blobs = float(weight), int(samples), int(min_blobs)
        self.volume, self.release = float(volume), bool(release)
        self.released = np.zeros((0, 3))  # anchors whose rows the loss no longer samples
        self.seed, self.canonical_time = int(seed), float(canonical_time)
        self.points = np.zeros((0, 3))  # (R, 3): each row's anchor mu
        self.times = np.zeros(0)  # (R,)
        self.targets = np.zeros((0, 3))  # (R, 3): the track's point at the row's time
        self.sizes = np.zeros(0)  # (R,): the object's radius, the virtual point's scale
        self.waiting = np.zeros((0, 7))  # anchors without Gaussians yet: mu, rgb, radius

    @classmethod
    def of(cls, carve_cfg, seed: int, canonical_time: float) -> "TrackAnchors":
        return cls(carve_cfg.anchor_weight, carve_cfg.anchor_samples,
                   carve_cfg.anchor_min_blobs, seed, canonical_time, carve_cfg.anchor_volume,
                   carve_cfg.anchor_release)

    @property
    def on(self) -> bool:
        return self.weight > 0.0

    def add(self, track, spacing: float, size: float) -> np.ndarray | None:
        """Anchor `track` (nehad.tracks.Track) with rows one frame `spacing` apart over its
        span; returns its mu (3,), or None when the track is too short to anchor. A track that
        continues an anchored one (`continues`) extends that anchor's path with its new times
        instead (the same mu): the tracks passes find an object in pieces, each pass the part
        no earlier chain draws."""
        if not self.on or len(track.blobs) < self.min_blobs:
            return None
        taus = np.arange(track.times[0], track.times[-1] + 1e-9, spacing)
        pts, _ = track.at(taus)
        mu = self.continues(taus, pts, spacing, size)
        if mu is not None:
            known, _ = self.path_of(mu)
            new = (taus < known[0] - 0.5 * spacing) | (taus > known[-1] + 0.5 * spacing)
            taus, pts = taus[new], pts[new]
        else:
            ref = float(np.clip(self.canonical_time, track.times[0], track.times[-1]))
            mu = track.at(np.array([ref]))[0][0]
            self.waiting = np.concatenate([self.waiting, np.concatenate(
                [mu, np.asarray(track.colour(), np.float64).reshape(3), [size]])[None]])
        n = len(taus)
        self.points = np.concatenate([self.points, np.repeat(mu[None], n, 0)])
        self.times = np.concatenate([self.times, taus])
        self.targets = np.concatenate([self.targets, pts])
        self.sizes = np.concatenate([self.sizes, np.full(n, size)])
        return mu

    def continues(self, taus: np.ndarray, pts: np.ndarray, spacing: float,
                  size: float) -> np.ndarray | None:
        """The mu of the anchored path that the path (`taus`, `pts`) continues, or None: its
        times overlap that path's span (give or take two spacings) and there its points lie a
        median of at most 2 `size` from the path's (the end's place past the span)."""
        for mu in np.unique(self.points, axis=0):
            known, where = self.path_of(mu)
            both = (taus >= known[0] - 2 * spacing) & (taus <= known[-1] + 2 * spacing)
            if not both.any():
                continue
            path = _along(np.clip(taus[both], known[0], known[-1]), known, where)
            if np.median(np.linalg.norm(pts[both] - path, axis=1)) <= 2.0 * size:
                return mu
        return None

    def ready(self, time_range: tuple[float, float] = (0.0, 1.0), spacing: float = 0.0,
              cover: float = 0.0) -> np.ndarray:
        """The anchors of the earlier passes that have no Gaussians yet and whose paths cover
        at least `cover` of `time_range` (rows `spacing` apart), (A, 7) rows of mu, rgb,
        radius; they count as having them from now on. Call before `add`."""
        lo, hi = time_range
        take = np.array([self.covered(row[:3], spacing) >= cover * (hi - lo)
                         for row in self.waiting], bool).reshape(-1)
        rows, self.waiting = self.waiting[take], self.waiting[~take]
        if self.release:
            self.released = np.concatenate([self.released, rows[:, :3]])
        return rows

    def covered(self, mu: np.ndarray, spacing: float) -> float:
        """How much of the time range the path anchored at `mu` covers: its distinct row
        times, one `spacing` each (with `spacing` 0, its span)."""
        taus, _ = self.path_of(mu)
        if not len(taus):
            return 0.0
        if spacing <= 0.0:
            return float(taus[-1] - taus[0])
        return float(len(np.unique(np.round(taus / spacing)))) * spacing

    def path_of(self, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(times (n,), points (n, 3)) of the track anchored at `mu`, in time order."""
        rows = np.nonzero(np.all(self.points == np.asarray(mu)[None], axis=1))[0]
        order = rows[np.argsort(self.times[rows], kind="stable")]
        return self.times[order], self.targets[order]

    def near_path(self, mu: np.ndarray, radius: float, means: np.ndarray,
                  times: np.ndarray, spacing: float) -> np.ndarray:
        """(M,) whether each point `means` at its time `times` lies within 2 `radius` of the
        path anchored at `mu` (its place interpolated at that time) and within one `spacing`
        of the path's span: the chain Gaussians that draw the anchored object."""
        taus, pts = self.path_of(mu)
        if not len(taus):
            return np.zeros(len(means), bool)
        inside = (times >= taus[0] - spacing) & (times <= taus[-1] + spacing)
        return inside & (np.linalg.norm(means - _along(times, taus, pts), axis=1) <= 2.0 * radius)

    def loss(self, model, step: int):
        """L_anchor of `step` (0.0 without anchors)."""
        if not self.on:
            return 0.0
        live = np.nonzero(~(self.points[:, None, :] == self.released[None]).all(2).any(1))[0]
        if len(live) == 0:
            return 0.0
        rng = np.random.default_rng([self.seed, int(step), 13])
        rows = live[rng.choice(len(live), min(self.samples, len(live)), replace=False)]
        field = model.field
        dtype = model.gaussians.means.dtype
        offsets = self._inside(rng, self.sizes[rows])
        mu = torch.as_tensor(self.points[rows] + offsets, dtype=dtype)
        log_scales = torch.log(torch.as_tensor(self.sizes[rows], dtype=dtype))[:, None].repeat(1, 3)
        quats = torch.zeros((len(rows), 4), dtype=dtype)
        quats[:, 0] = 1.0
        t = torch.as_tensor(self.times[rows], dtype=dtype)[:, None]
        t_eq = torch.full((len(rows), 1), self.canonical_time, dtype=dtype)
        out = field(mu, log_scales, quats, t, mu, t_eq)
        miss = out.means - torch.as_tensor(self.targets[rows] + offsets, dtype=dtype)
        extent = float(field.extent)
        return self.weight * (miss * miss).sum(dim=1).mean() / (extent * extent)

    def _inside(self, rng, radii: np.ndarray) -> np.ndarray:
        """(n, 3) offsets uniform in balls of `radii` (`volume` times the object's radius), 0
        with `volume` 0: the points of the object about its anchor, each carried along the
        track by the same offset (a rigid translation)."""
        if self.volume <= 0.0:
            return np.zeros((len(radii), 3))
        u = rng.normal(size=(len(radii), 3))
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        return u * (self.volume * radii * rng.random(len(radii)) ** (1.0 / 3.0))[:, None]

    def state_dict(self) -> dict:
        return {"points": torch.as_tensor(self.points), "times": torch.as_tensor(self.times),
                "targets": torch.as_tensor(self.targets), "sizes": torch.as_tensor(self.sizes),
                "released": torch.as_tensor(self.released),
                "waiting": torch.as_tensor(self.waiting)}

    def load_state_dict(self, state: dict | None) -> None:
        if not state:
            return
        self.points = state["points"].numpy().reshape(-1, 3)
        self.times = state["times"].numpy().reshape(-1)
        self.targets = state["targets"].numpy().reshape(-1, 3)
        self.sizes = state["sizes"].numpy().reshape(-1)
        if "released" in state:
            self.released = state["released"].numpy().reshape(-1, 3)
        self.waiting = state["waiting"].numpy().reshape(-1, 7)


def _along(at: np.ndarray, taus: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(n, 3): the path through `pts` (m, 3) at its times `taus` (increasing), interpolated
    linearly at the times `at` (held at its ends outside them)."""
    return np.stack([np.interp(at, taus, pts[:, k]) for k in range(3)], axis=1)


__all__ = ["TrackAnchors"]
