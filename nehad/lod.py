"""Layered progressive optimisation for streaming (docs/streaming.md; the paper's appendix,
"Detailed Methodology of Streaming", after LapisGS): G_i = G_0 + sum_{j <= i} dG_j.

`LayeredSchedule` is the schedule (`nehad.schedule`) the ordinary `nehad.trainer.Trainer` follows
when lod.levels = L > 1:

* Layer 0 is the ordinary schedule (`StagedSchedule`: coarse static stage, then the fine stage
  with the deformation field) on images downscaled by data.downscale * 2^(L-1), the lowest
  resolution.
* Layer k >= 1 runs `lod.iterations` fine steps (0: fine.iterations) on images at
  data.downscale * 2^(L-1-k), twice the resolution of layer k-1. It starts by spawning one child
  per Gaussian of the layers below that lives at every time (not from carving's chains):
  position drawn from the parent's Gaussian, half its scale (the pixels are half as large),
  opacity `lod.spawn_opacity`, colour, rotation and BED equilibrium (mu_eq, t_eq) inherited,
  as densified children inherit them. Only the new layer
  trains: the Gaussians of earlier layers get no gradient (zeroed before each Adam step, and
  restored bit-exactly after it), are never densified, pruned or opacity-reset
  (`LayeredSchedule.densify_limits`). The deformation field is shared by all layers; it trains in layer
  0 and stays fixed in later layers unless `lod.train_field` (fixed keeps every prefix of layers
  rendering exactly as it did when it was trained).
* At the end of every layer its Gaussians with opacity < `lod.opacity_threshold` are dropped: the
  threshold sets how many Gaussians (bytes) each layer adds (paper: "adjusting the opacity
  threshold ... to fine-tune transmitted rates").

Gaussians are stored layer by layer (layer 0 first), so layer k is a contiguous index range;
RUN/model.pt holds `layer` ([N] int32, each Gaussian's layer) and `lod` (levels, per-layer counts
and downscales). Checkpoints hold the per-layer counts, so a run resumes inside any layer.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from nehad.curriculum import TimeWindow
from nehad.densify import append_gaussians, keep_gaussians, spawn_children
from nehad.schedule import Phase, Schedule, StagedSchedule

if TYPE_CHECKING:
    from nehad.model import RunInfo
    from nehad.trainer import Trainer, Views


def layer_downscales(levels: int, downscale: int) -> list[int]:
    """Image downscale of each layer: layer 0 the coarsest, the last one `downscale`."""
    return [int(downscale) * 2 ** (levels - 1 - k) for k in range(levels)]


def layer_ids(layer_sizes) -> np.ndarray:
    """[N] int32 layer index of each Gaussian from the per-layer counts (layers contiguous)."""
    return np.repeat(np.arange(len(layer_sizes), dtype=np.int32),
                     np.asarray(layer_sizes, np.int64)).astype(np.int32)


class LayeredSchedule:
    """`cfg.lod.levels` layers (see the module doc): layer 0 follows `StagedSchedule` at the
    lowest resolution, then each enhancement layer trains `lod.iterations` fine steps on its own
    Gaussians while the layers below stay frozen."""

    def __init__(self, cfg):
        self.cfg = cfg
        self.base = StagedSchedule(cfg)  # layer 0
        self.levels = int(cfg.lod.levels)
        self.layer_iterations = int(cfg.lod.iterations or cfg.fine.iterations)
        if self.levels > 1 and self.layer_iterations < 1:
            from nehad.configtools import ConfigError

            raise ConfigError("lod.iterations: enhancement layers need >= 1 step (lod.iterations "
                              "and fine.iterations are both 0)")
        self.base_steps = self.base.total_steps
        self.total_steps = self.base_steps + (self.levels - 1) * self.layer_iterations
        self.downscales = layer_downscales(self.levels, cfg.data.downscale)
        #: Gaussian counts of the finished (frozen) layers, in order.
        self.layer_sizes: list[int] = []
        self._views: dict = {}
        self._snapshot: dict = {}

    # -- where a step falls -------------------------------------------------------------------
    def layer_of(self, step: int) -> int:
        """The layer trained at (0-based) `step`."""
        if step < self.base_steps:
            return 0
        return min(1 + (step - self.base_steps) // self.layer_iterations, self.levels - 1)

    def layer_end(self, layer: int) -> int:
        """The number of steps done when `layer` is finished."""
        return self.base_steps + layer * self.layer_iterations

    def phase(self, step: int) -> Phase:
        if step < self.base_steps:
            return self.base.phase(step)
        return Phase("fine", (step - self.base_steps) % self.layer_iterations,
                     self.layer_iterations, self.layer_of(step))

    def stage_config(self, phase: Phase):
        return self.base.stage_config(phase)

    def views(self, trainer: Trainer, layer: int) -> Views:
        """Training views of `layer` at its resolution (loaded once; the last layer's are the
        trainer's own, at data.downscale)."""
        if layer == self.levels - 1:
            return trainer.train_views
        if layer not in self._views:
            self._views[layer] = trainer.load_views(self.downscales[layer])
        return self._views[layer]

    def resolution_warmup(self, step: int, phase: Phase) -> tuple[int, int] | None:
        """Layer 0 follows data.resolution_schedule over its own steps; enhancement layers
        train at their layer's resolution throughout."""
        return (step, self.base_steps) if phase.layer == 0 else None

    def time_window(self, trainer: Trainer, phase: Phase) -> TimeWindow:
        """Enhancement layers see every time: the time curriculum (nehad.curriculum) belongs to
        layer 0, where the shared field learns to follow the objects."""
        if phase.layer > 0:
            return TimeWindow(*trainer.scene.time_range)
        return self.base.time_window(trainer, phase)

    def frozen_groups(self, phase: Phase) -> frozenset[str]:
        """Layer 0 as the staged schedule; later layers keep the shared field fixed unless
        lod.train_field."""
        if phase.layer == 0:
            return self.base.frozen_groups(phase)
        return frozenset() if self.cfg.lod.train_field else frozenset({"grid", "decoder"})

    # -- setup and state ----------------------------------------------------------------------
    def attach(self, trainer: Trainer, state: dict | None) -> None:
        """Restore the finished layers of a resumed run and freeze them."""
        saved = (state or {}).get("lod") or {}
        self.layer_sizes = [int(v) for v in saved.get("layer_sizes", [])]
        self._snapshot = self._take_snapshot(trainer)

    def lod_state(self) -> dict:
        return {"levels": self.levels, "layer_sizes": list(self.layer_sizes),
                "downscales": list(self.downscales), "iterations": self.layer_iterations,
                "opacity_threshold": float(self.cfg.lod.opacity_threshold)}

    def state_dict(self) -> dict:
        return {"lod": self.lod_state()}

    def model_extras(self, trainer: Trainer) -> dict:
        sizes = list(self.layer_sizes)
        rest = len(trainer.model.gaussians) - sum(sizes)
        if rest:  # an unfinished layer (model_state of a run stopped early)
            sizes.append(rest)
        return {"layer": torch.from_numpy(layer_ids(sizes)),
                "lod": {**self.lod_state(), "layer_sizes": sizes}}

    @property
    def frozen(self) -> int:
        """The Gaussians of the finished layers (stored first)."""
        return sum(self.layer_sizes)

    def densify_limits(self, phase: Phase) -> tuple[int, int]:
        """The finished layers stay as they are; the cap of the layer: `lod.base_max_gaussians`
        for layer 0 when set, else `densify.max_gaussians` (which counts only the trainable
        Gaussians, i.e. this layer's)."""
        base_cap = int(self.cfg.lod.base_max_gaussians)
        cap = base_cap if phase.layer == 0 and base_cap > 0 else self.cfg.densify.max_gaussians
        return self.frozen, cap

    def ends_stage(self, steps_done: int) -> bool:
        return steps_done in (self.cfg.coarse.iterations, self.total_steps)

    # -- freezing -----------------------------------------------------------------------------
    def _take_snapshot(self, trainer: Trainer) -> dict:
        f = self.frozen
        g = trainer.model.gaussians
        return {name: getattr(g, name).detach()[:f].clone() for name in g.NAMES}

    def before_update(self, trainer: Trainer) -> None:
        """The frozen layers get no gradient."""
        f = self.frozen
        if f:
            names = set(trainer.model.gaussians.NAMES)
            for group in trainer.optimizer.param_groups:
                if group["name"] in names:
                    p = group["params"][0]
                    if p.grad is not None:
                        p.grad[:f] = 0.0

    @torch.no_grad()
    def after_update(self, trainer: Trainer, phase: Phase, window: TimeWindow) -> None:
        """The frozen layers are restored bit-exactly (Adam's momentum would still move them);
        then the staged schedule's rule (the time curriculum's held rows)."""
        f = self.frozen
        if f:
            g = trainer.model.gaussians
            for name in g.NAMES:
                getattr(g, name)[:f] = self._snapshot[name]
        self.base.after_update(trainer, phase, window)

    # -- layer boundaries ---------------------------------------------------------------------
    def begin(self, trainer: Trainer, phase: Phase) -> None:
        if phase.layer == 0:
            self.base.begin(trainer, phase)
        else:
            self._spawn_layer(trainer, phase.layer)

    def end(self, trainer: Trainer, phase: Phase, step: int, record: dict) -> None:
        record["layer"] = phase.layer
        if step + 1 == self.layer_end(phase.layer):
            self._finish_layer(trainer, phase.layer)
            record["layer_sizes"] = list(self.layer_sizes)
            record["gaussians"] = len(trainer.model.gaussians)

    @torch.no_grad()
    def _spawn_layer(self, trainer: Trainer, layer: int) -> None:
        """Seed layer `layer`: one child per frozen Gaussian that lives at every time (see the
        module doc). Carving's chains (a finite life, nehad.carve_pass) have no children here: a
        child would inherit the life, and the split-layer export carries lives in layer 0 only
        (docs/design.md section 8.1)."""
        g = trainer.model.gaussians
        f = self.frozen
        gen = torch.Generator().manual_seed(int(self.cfg.train.seed) * 1_000_003 + 7919 * layer)
        parents = torch.zeros(len(g), dtype=torch.bool)
        parents[:f] = ~g.mortal()[:f]
        new = spawn_children(g, parents, 1, gen)
        new["log_scales"] = new["log_scales"] - math.log(2.0)
        p = float(self.cfg.lod.spawn_opacity)
        new["opacity_logits"] = torch.full_like(new["opacity_logits"], math.log(p / (1.0 - p)))
        append_gaussians(g, trainer.optimizer, new)
        trainer.densify_state.reset(len(g))
        trainer.log_event(f"layer {layer}: {f} frozen Gaussians, {len(new['means'])} spawned, "
                          f"images at 1/{self.downscales[layer]}")

    @torch.no_grad()
    def _finish_layer(self, trainer: Trainer, layer: int) -> None:
        """Drop the layer's Gaussians below the opacity threshold; freeze the rest."""
        g = trainer.model.gaussians
        f = self.frozen
        keep = torch.ones(len(g), dtype=torch.bool)
        opacity = torch.sigmoid(g.opacity_logits[f:].reshape(-1))
        keep[f:] = opacity >= self.cfg.lod.opacity_threshold
        if len(g) > f and not bool(keep[f:].any()):
            # a threshold above every opacity would leave an empty layer: keep it whole
            trainer.warn(f"warning: lod.opacity_threshold {self.cfg.lod.opacity_threshold:g} is "
                         f"above every opacity of layer {layer} (max {float(opacity.max()):.3g}); "
                         f"the layer is kept unthresholded")
            keep[f:] = True
        if not bool(keep.all()):
            keep_gaussians(g, trainer.optimizer, keep)
        self.layer_sizes.append(len(g) - f)
        trainer.densify_state.reset(len(g))
        self._snapshot = self._take_snapshot(trainer)


def run_layers(info: RunInfo, n: int) -> np.ndarray:
    """[n] int32 layer of each Gaussian of a loaded run (all 0 for a run without layers)."""
    if info.layer is None:
        return np.zeros(n, np.int32)
    arr = np.asarray(info.layer, np.int32)
    if arr.shape != (n,):
        raise ValueError(f"model.pt: 'layer' has shape {arr.shape}, expected ({n},)")
    return arr


def schedule_for(cfg) -> Schedule:
    """The schedule `cfg` asks for: `LayeredSchedule` when lod.levels > 1, else
    `nehad.schedule.StagedSchedule`. It lives here, above both, so that nehad.schedule need not
    import this module (no import circle)."""
    return LayeredSchedule(cfg) if cfg.lod.levels > 1 else StagedSchedule(cfg)


__all__ = ["LayeredSchedule", "layer_downscales", "layer_ids", "run_layers", "schedule_for"]
