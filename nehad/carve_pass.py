"""Residual carving inside training (docs/training.md, "Objects that are never created"): when a
pass runs, which views it looks at, and how its Gaussians join the model. The geometry (which
pixels are unexplained, where their rays agree) is `nehad.carve`'s.

`ResidualCarving` is a strategy beside `nehad.densify.DensifyStrategy`: the trainer builds it
once from the config and calls `step_post_update` after densification, passing in the model,
the optimizer, the densification state and where the step falls; it never reads the trainer."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nehad.chain_check import (DROPPED, HALO, chain_lives, fill_untrained, trained_away,
                                trained_rows)
from nehad.config import CarveConfig
from nehad.curriculum import TimeWindow, eligible_frames
from nehad.densify import DensifySchedule, DensifyState, append_gaussians, keep_gaussians
from nehad.views import render_views


def van_der_corput(i: int) -> float:
    """The i-th point (i >= 1) of the base-2 van der Corput sequence in [0, 1): 0.5, 0.25,
    0.75, 0.125, ...; any run of consecutive points spreads evenly over [0, 1)."""
    x, f = 0.0, 0.5
    while i > 0:
        x += f * (i & 1)
        i >>= 1
        f *= 0.5
    return x


@dataclass(frozen=True)
class ResidualCarving:
    """Carving passes every `cfg.every` iterations of a stage's densification window, or at the
    fractions `cfg.at` of it (a CarveConfig, nehad.config). `box`: the scene box rays are
    sampled in; `free_offset`: how far from its equilibrium a carved Gaussian is put with
    `cfg.hold` false (the BED position mask then at its floor: `free_offset_of`)."""

    cfg: CarveConfig
    seed: int
    canonical_time: float
    max_gaussians: int
    box: np.ndarray
    background: tuple
    free_offset: float

    def due(self, deforms: bool, layer: int, it: int, timing: DensifySchedule) -> bool:
        """Whether a pass runs after iteration `it` (1-based) of a stage: inside the
        densification window, never while opacities recover from a reset, never in streaming
        layers above the base; every `every` iterations, or with `every` 0 at the iterations of
        `pass_iterations`."""
        c = self.cfg
        if c.max_new <= 0 or layer > 0 or (not deforms and not c.static_stage):
            return False
        if c.every <= 0:
            return it in pass_iterations(c.at, timing, self._recovery())
        if c.mode == "tracks" and timing.recovering(it, 0.5):
            return False  # every view is rendered: not while opacities grow back
        return not (not timing.start <= it < timing.stop or it % c.every
                    or it < c.start * timing.length or timing.recovering(it))

    def _recovery(self) -> float:
        """The part of an opacity-reset period a pass waits out: half of it for tracks (every
        view is rendered and read), a quarter otherwise."""
        return 0.5 if self.cfg.mode == "tracks" else 0.25

    def _pass_index(self, it: int, timing: DensifySchedule) -> int:
        """1, 2, ... for the passes of a stage in order (picks the pass's time)."""
        c = self.cfg
        if c.every > 0:
            return it // c.every
        return 1 + sorted(pass_iterations(c.at, timing, self._recovery())).index(it)

    def step_post_update(self, model, optimizer, state: DensifyState, *, deforms: bool,
                         layer: int, it: int, step: int, window: TimeWindow, views,
                         degree: int, timing: DensifySchedule, priors=None) -> dict:
        """One pass when due (see `due`): the views nearest to one time (the canonical time in
        the static stage; in the deforming stage the frame time nearest to the next point of a
        van der Corput sequence over the window, so that passes cover the time range evenly),
        each rendered at its own time; returns what it did."""
        if not self.due(deforms, layer, it, timing):
            return {}
        rng = np.random.default_rng([self.seed, step, 7])
        if self.cfg.mode == "tracks":
            return self._track_pass(model, optimizer, state, deforms, window, views, degree,
                                    priors)
        t_c, nearest = self._pass_views(deforms, self._pass_index(it, timing), window, views)
        pts, cols, widths, n_bad = self._find_points(model, deforms, nearest, views, degree, rng)
        most = self._most_new()
        if len(pts) > most:
            pick = rng.choice(len(pts), most, replace=False)
            pts, cols, widths = pts[pick], cols[pick], widths[pick]
        out = {"carve_time": round(t_c, 4), "carve_unexplained": n_bad, "carved": len(pts)}
        if len(pts):
            out.update(self._add(model.gaussians, optimizer, state, pts, cols, widths, t_c,
                                 deforms, views))
        return out

    def _pass_views(self, deforms: bool, index: int, window: TimeWindow, views):
        """(the time of the stage's `index`-th pass, the indices of the views nearest to it)."""
        c = self.cfg
        pool = eligible_frames(views.times, window)
        times = np.asarray(views.times, np.float64)
        if deforms:  # the passes' times spread evenly over the window (van der Corput)
            at = window.lo + (window.hi - window.lo) * van_der_corput(index)
            t_c = float(times[pool[np.argmin(np.abs(times[pool] - at))]])
        else:
            t_c = float(self.canonical_time)
        count = c.seed_views if c.mode == "rays" else c.views
        return t_c, pool[np.argsort(np.abs(times[pool] - t_c), kind="stable")[:count]]

    def _find_points(self, model, deforms: bool, nearest, views, degree: int, rng):
        """Points, colours and widths where the views disagree with the model
        (`nehad.carve.seed_rays` or `carve_points`), and the number of unexplained pixels."""
        from nehad.carve import carve_points, seed_rays

        c = self.cfg
        times = np.asarray(views.times, np.float64)
        cams, targets, alphas, drawn = render_views(model, deforms, nearest, views, degree,
                                                    self.background)
        if c.mode == "rays":
            return seed_rays(cams, targets, alphas, [d.rgb for d in drawn], self.box,
                             residual=c.residual, stride=c.stride,
                             depth_samples=c.depth_samples, rng=rng)
        return carve_points(
            cams, targets, alphas, [d.rgb for d in drawn], self.box, times[nearest],
            render_alphas=[d.alpha for d in drawn], render_depths=[d.depth for d in drawn],
            residual=c.residual, stride=c.stride, depth_samples=c.depth_samples,
            min_views=c.min_views, agree=c.agree, colour_tol=c.colour_tol, motion=c.motion,
            rng=rng)

    def _track_pass(self, model, optimizer, state: DensifyState, deforms: bool,
                    window: TimeWindow, views, degree: int, priors=None) -> dict:
        """`carve.mode=tracks` (nehad.tracks): every view of the window rendered at its own
        time; the tracks of its unexplained blobs become chains of Gaussians, one every frame
        spacing along each track, living around their own time and moving with the track,
        except where the model already draws the object (`nehad.tracks.drawn_already`)."""
        from nehad.tracks import (TrackSettings, cluster_seeds, find_blobs, fit_tracks,
                                  seeds_along)

        c = self.cfg
        pool = eligible_frames(views.times, window)
        times = np.asarray(views.times, np.float64)
        clouds = []
        cams, targets, alphas, drawn = render_views(model, deforms, pool, views, degree,
                                                    self.background, clouds)
        blobs = find_blobs(cams, times[pool], targets, alphas, [d.rgb for d in drawn],
                           residual=c.residual)
        tracks = fit_tracks(cams, blobs, TrackSettings(max_tracks=c.max_tracks))
        spacing = frame_spacing(times) or 1.0
        out = {"carve_blobs": len(blobs), "carve_tracks": len(tracks), "carved": 0}
        if deforms and priors is not None and priors.spins.on:  # before this pass's chains
            out["spin_bodies"] = priors.spins.find(model, views, degree, self.background, c,
                                                   spacing)
        anchors = None if priors is None else priors.anchors
        seeds = [seeds_along(tr, cams, spacing, 0.0, 1.0, c.track_width) for tr in tracks]
        if not seeds:
            return out
        if anchors is not None and anchors.on:
            out.update(self._anchor(model.gaussians, optimizer, state, tracks, seeds, spacing,
                                    anchors, views))
        pts, vel, t_eq, cols, widths, shapes = (np.concatenate(x) for x in zip(*seeds))
        have = self._drawn_already(pts, vel, t_eq, cols, widths, times[pool], clouds)
        out["carve_drawn"] = int(have.sum())
        most = self._most_new() // c.track_members  # whole seeds
        pts, vel, t_eq, cols, widths, shapes = cluster_seeds(
            *(x[~have][:most] for x in (pts, vel, t_eq, cols, widths, shapes)), c.track_members)
        out["carved"] = len(pts)
        if len(pts):
            out.update(self._add(model.gaussians, optimizer, state, pts, cols, widths, t_eq,
                                 deforms, views, velocities=vel, shapes=shapes))
        return out

    def _anchor(self, g, optimizer, state, tracks, seeds, spacing, anchors, views) -> dict:
        """`carve.anchor_weight`: each long track anchored (nehad.track_anchors), and
        `anchor_members` Gaussians that live at every time added at each anchor of the
        earlier passes (whose paths the field has been learning since)."""
        from nehad.tracks import cluster_seeds

        times = np.asarray(views.times, np.float64)
        ready = anchors.ready((float(times.min()), float(times.max())), spacing,
                              self.cfg.anchor_cover)
        found = 0
        for track, seed in zip(tracks, seeds):
            size = float(seed[4][0])  # the seeds' scale: track_width object radii
            found += anchors.add(track, spacing, size / self.cfg.track_width) is not None
        out = {}
        if len(ready):
            if self.cfg.anchor_replace:
                out["anchor_replaced"] = self._unchain(g, optimizer, state, ready, anchors,
                                                       spacing)
            n = len(ready)
            sizes = self.cfg.track_width * ready[:, 6]
            pts, _, _, cols, widths, shapes = cluster_seeds(
                ready[:, :3], np.zeros((n, 3)), np.full(n, anchors.canonical_time),
                ready[:, 3:6], sizes, sizes[:, None, None] * np.eye(3)[None],
                self.cfg.anchor_members)
            self._add(g, optimizer, state, pts, cols, widths, anchors.canonical_time, False,
                      views, shapes=shapes)
        return {"anchored": found, "anchor_gaussians": len(ready) * self.cfg.anchor_members,
                **out}

    @staticmethod
    def _unchain(g, optimizer, state, ready, anchors, spacing: float) -> int:
        """`carve.anchor_replace`: the chain Gaussians (finite life) on the paths of the
        anchors `ready` are removed; how many."""
        mortal = g.mortal().numpy()
        if not mortal.any():
            return 0
        means = g.means.detach().numpy().astype(np.float64)
        t_eq = g.t_eq.detach().reshape(-1).numpy().astype(np.float64)
        gone = np.zeros(len(means), bool)
        for row in ready:
            gone |= anchors.near_path(row[:3], float(row[6]), means, t_eq, spacing)
        gone &= mortal
        if gone.any():
            keep = torch.as_tensor(~gone)
            keep_gaussians(g, optimizer, keep)
            if state.grad_accum.shape[0] == len(keep):
                state.keep(keep, 0)
        return int(gone.sum())

    def _drawn_already(self, pts, vel, t_eq, cols, widths, view_times, clouds) -> np.ndarray:
        """Which seeds stand for an object the model already draws at their time, judged on
        the model at the nearest rendered view's time (the reach grows by how far the seed
        moves in between); with the object's radius (widths / track_width) as the reach."""
        from nehad.tracks import drawn_already

        have = np.zeros(len(pts), bool)
        if not clouds:
            return have
        nearest = np.abs(t_eq[:, None] - view_times[None, :]).argmin(axis=1)
        reach = (widths / max(self.cfg.track_width, 1e-6)
                 + np.linalg.norm(vel, axis=1) * np.abs(t_eq - view_times[nearest]))
        for k in np.unique(nearest):
            rows = np.nonzero(nearest == k)[0]
            cl = clouds[k]
            have[rows] = drawn_already(pts[rows], cols[rows], reach[rows], cl.means,
                                       cl.opacities, cl.base_rgb(), self.cfg.colour_tol)
        return have

    def check_chains(self, model, views, degree: int, spacing: float, train_times=()) -> dict:
        """`carve.check_split`: after training, the chains of Gaussians the tracks passes
        seeded are found again (`nehad.tracks.chains_of`); a member grown past HALO times its
        chain's median size is shrunk to it; then each chain is kept, kept with its life
        multiplied by one of `carve.check_lives`, or made transparent (opacity ~1e-13; the rows
        stay, so streaming layers keep their sizes), whichever brings the `views` (held-out
        views: the data's validation split) around its times closest to their targets
        (`nehad.chain_check.chain_lives`). A junk track, or a second copy of an object the
        field already draws, costs there what it would cost at the test times
        (docs/training.md)."""
        from nehad.model import cloud_at
        from nehad.tracks import chains_of

        g = model.gaussians
        mortal = np.nonzero(g.mortal().numpy())[0]
        if not len(mortal) or views is None or not len(views.times):
            return {}
        with torch.no_grad():
            means = g.means.detach().numpy()[mortal]
            vel = g.velocity.detach().numpy()[mortal]
            t_eq = g.t_eq.detach().reshape(-1).numpy()[mortal]
            reach = 2.0 * np.exp(g.log_scales.detach().numpy()[mortal]).max(axis=1)
        labels = chains_of(means, vel, t_eq, spacing, reach)
        grown = self._shrink_halos(g, mortal, labels, reach)
        chains = [mortal[labels == c] for c in range(labels.max() + 1)]
        rates = g.life_rate.detach().reshape(-1).numpy().astype(np.float64)
        t_all = g.t_eq.detach().reshape(-1).numpy()  # every row's, as chain_lives indexes
        trained = trained_rows(t_all, rates, train_times)
        filled = self._fill(g, chains, t_all, trained) if self.cfg.check_fill else 0
        with torch.no_grad():  # clouds without the life factors; the chains' lives are chosen
            g.life_rate[torch.as_tensor(mortal)] = 1e-20  # still finite: the drift holds
            try:
                choice = chain_lives(chains, t_all, rates, lambda t: cloud_at(model, t, degree),
                                     views, self.background, self.cfg.check_lives,
                                     trained=trained, pieces=self.cfg.check_pieces)
            finally:
                g.life_rate[torch.as_tensor(mortal), 0] = torch.as_tensor(
                    rates[mortal], dtype=g.life_rate.dtype)
            opacity = torch.sigmoid(g.opacity_logits).reshape(-1).numpy()
            away = trained_away(chains, trained, opacity)
            for c in away:
                choice[chains[c]] = DROPPED
            rows = torch.as_tensor(np.nonzero(choice == DROPPED)[0])
            g.opacity_logits[rows] = -30.0
            longer = torch.as_tensor(np.nonzero(choice > 1.0)[0])
            g.life_rate[longer] = g.life_rate[longer] / torch.as_tensor(
                choice[longer.numpy()], dtype=g.life_rate.dtype)[:, None]
        dropped = [c for c, rows in enumerate(chains) if (choice[rows] == DROPPED).all()]
        return {"chains": len(chains), "chains_dropped": len(dropped),
                "chain_gaussians_dropped": int(sum(len(chains[c]) for c in dropped)),
                "chain_gaussians_longer": int((choice > 1.0).sum()),
                "chains_cut": sum(1 for rows in chains
                                  if 0 < (choice[rows] == DROPPED).sum() < len(rows)),
                "halo_gaussians_shrunk": int(grown.sum()), "untrained_filled": filled,
                "chains_trained_away": len(away)}

    @staticmethod
    def _shrink_halos(g, mortal, labels, reach) -> np.ndarray:
        """Each member of a chain of 3 or more (`labels` over the `mortal` rows) whose `reach`
        is more than HALO times its chain's median (a halo) shrunk back to that median (it
        still draws the object); which members were, one flag per mortal row."""
        grown, size = np.zeros(len(mortal), bool), np.zeros(len(mortal))
        for c in range(labels.max() + 1):
            rows = labels == c
            if rows.sum() >= 3:
                size[rows] = 0.5 * np.median(reach[rows])
                grown[rows] = reach[rows] > HALO * 2.0 * size[rows]
        with torch.no_grad():
            rows = torch.as_tensor(mortal[grown])
            cap = torch.log(torch.as_tensor(size[grown], dtype=g.log_scales.dtype))[:, None]
            g.log_scales[rows] = torch.minimum(g.log_scales[rows], cap)
        return grown

    @staticmethod
    def _fill(g, chains, t_all, trained) -> int:
        """`carve.check_fill`: each chain's untrained members (`trained` False, one flag per
        row) take their trained neighbours' appearance and shape
        (`nehad.chain_check.fill_untrained`); how many changed."""
        names = ("sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats")
        count = 0
        with torch.no_grad():
            for rows in chains:
                if trained[rows].all() or not trained[rows].any():
                    continue
                index = torch.as_tensor(rows)
                for name in names:
                    p = getattr(g, name)
                    flat = p.detach()[index].reshape(len(rows), -1).numpy()
                    new = fill_untrained(t_all[rows], trained[rows], flat)
                    p[index] = torch.as_tensor(new, dtype=p.dtype).reshape(p[index].shape)
                q = g.quats.detach()[index]  # interpolated quaternions, made unit again
                g.quats[index] = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
                count += int((~trained[rows]).sum())
        return count

    def _most_new(self) -> int:
        """Gaussians one pass may add: `max_new`, and never more than the cap."""
        cap = self.max_gaussians
        return min(self.cfg.max_new, cap) if cap > 0 else self.cfg.max_new

    def _add(self, g, optimizer, state: DensifyState, pts, cols, widths, t_c,
             deforms: bool, views, velocities=None, shapes=None) -> dict:
        """Append the carved Gaussians; at the cap the least opaque ones make room first (they
        are relocated, nehad.carve)."""
        from nehad.carve import new_gaussians

        out = {}
        cap = self.max_gaussians
        over = len(g) + len(pts) - cap if cap > 0 else 0
        keep = torch.ones(len(g), dtype=torch.bool)
        if over > 0:
            keep[torch.argsort(g.opacity_logits.detach().reshape(-1))[:min(over, len(g))]] = False
            keep_gaussians(g, optimizer, keep)
            out["relocated"] = int((~keep).sum())
        life = self.cfg.life * frame_spacing(views.times) if deforms else 0.0
        append_gaussians(g, optimizer,
                         new_gaussians(pts, cols, widths, t_c, g, self.cfg.opacity, life,
                                       0.0 if self.cfg.hold else self.free_offset,
                                       velocities, shapes))
        if state.grad_accum.shape[0] == len(keep):  # statistics follow
            state.keep(keep, len(pts))
        return out


def check_run_chains(carving: ResidualCarving, model, cfg, data_dir, run, step: int,
                     load_background, train_views, degree: int) -> dict:
    """`carve.check_split` after a run's last step: the tracks chains of `model` checked on
    that split of the data (`ResidualCarving.check_chains`), then, with `carve.carry_steps` >
    0 and no streaming layers, the carried objects (`nehad.carry_stage`), judged on the same
    split; written to RUN/tracks_check.json (RUN/metrics.jsonl keeps one record per logged
    step); {} when the run is not in tracks mode, has no chain, or the data has no such split."""
    import json

    from nehad.data.loader import load_dataset
    from nehad.runtime.images import atomic_write_bytes
    from nehad.views import views_of

    split, g = cfg.carve.check_split, model.gaussians
    carries = cfg.carve.carry_steps > 0 and cfg.lod.levels <= 1
    if not split or cfg.carve.mode != "tracks" or len(g) == 0:
        return {}
    if not g.has_life() and not (carries and cfg.carve.carry_spin):
        return {}
    try:
        scene = load_dataset(data_dir, splits=(split,), background=load_background,
                             downscale=cfg.data.downscale, frame_stride=cfg.data.frame_stride)
    except (ValueError, OSError, KeyError):
        return {}  # no such split: nothing to check against
    train_times = train_views.times
    held_out = views_of(scene, split)
    did = (carving.check_chains(model, held_out, degree, frame_spacing(train_times), train_times)
           if g.has_life() else {})
    if (did or cfg.carve.carry_spin) and carries:
        from nehad.carry_stage import carry_stage

        did.update(carry_stage(model, train_views, held_out, cfg.carve, degree,
                               carving.background, frame_spacing(train_times),
                               (min(train_times), max(train_times)), cfg.train.seed))
    if did:
        record = {"step": step, "split": split, **did}
        atomic_write_bytes(Path(run) / "tracks_check.json", json.dumps(record).encode())
    return did


def pass_iterations(fractions, timing: DensifySchedule, recovery: float) -> set:
    """The iterations (1-based) of a stage at which the passes of `carve.at` run: each fraction
    of the stage's length, moved past the first `recovery` part of an opacity-reset period it
    falls in (opacities are still growing back there), kept when inside the densification
    window."""
    out = set()
    for frac in fractions:
        it = max(int(round(frac * timing.length)), 1)
        while timing.recovering(it, recovery):
            it += 1
        if timing.start <= it < timing.stop:
            out.add(it)
    return out


def frame_spacing(times) -> float:
    """The median spacing of the distinct training times (0 with a single time)."""
    distinct = np.unique(np.asarray(times, np.float64))
    return float(np.median(np.diff(distinct))) if len(distinct) > 1 else 0.0


def pin_mortal(g) -> None:
    """`carve.pin`: zero the gradients of the place, motion, time and life of the Gaussians with
    a finite life (call between backward and the optimizer step). A track's Gaussian is seen by
    one or two training views, which can slide it along their rays at no cost while every other
    camera sees it move; its place and motion from the track are a fit to the rays of many views
    (nehad.tracks). Their colour, opacity and shape are still learnt (with the shape held too,
    the 100x100 occluder's sphere scored 1.2 dB less: docs/results.md); with Adam's moments at
    zero from the start, a parameter whose gradient is always zero does not move."""
    mortal = g.mortal()
    if not bool(mortal.any()):
        return
    for name in ("means", "velocity", "t_eq", "life_rate", "mu_eq"):
        grad = getattr(g, name).grad
        if grad is not None:
            grad[mortal] = 0.0


def free_offset_of(field_cfg, extent: float) -> float:
    """A distance from a Gaussian to its equilibrium at which the BED position mask is at its
    floor gamma to float32 precision (dd = 12 sigma_s: exp(-72) ~ 1e-31)."""
    return 12.0 * field_cfg.sigma_s_fraction * float(extent)


__all__ = ["ResidualCarving", "check_run_chains", "frame_spacing",
           "free_offset_of", "pass_iterations", "pin_mortal", "van_der_corput"]
