"""Layered progressive optimisation for streaming (SPEC 8; paper appendix "Detailed Methodology of
Streaming", after LapisGS): G_i = G_0 + sum_{j <= i} dG_j.

`LodTrainer` drives the ordinary :class:`nehad.trainer.Trainer` through L = `lod.levels` layers:

* Layer 0 is the ordinary schedule (coarse static stage, then the fine stage with the deformation
  field) on images downscaled by data.downscale * 2^(L-1), the lowest resolution.
* Layer k >= 1 runs `lod.iterations` fine steps (0: fine.iterations) on images at
  data.downscale * 2^(L-1-k), twice the resolution of layer k-1. It starts by spawning one child
  per Gaussian of the layers below: position drawn from the parent's Gaussian, half its scale
  (the pixels are half as large), opacity `lod.spawn_opacity`, colour, rotation and BED
  equilibrium (mu_eq, t_eq) inherited (SPEC 4.7: children inherit). Only the new layer trains:
  the Gaussians of earlier layers get no gradient (zeroed before each Adam step, and restored
  bit-exactly after it), are never densified, pruned or opacity-reset (`DensifyStrategy.frozen`).
  The deformation field is shared by all layers; it trains in layer 0 and stays fixed in later
  layers unless `lod.train_field` (fixed keeps every prefix of layers rendering exactly as it did
  when it was trained).
* At the end of every layer its Gaussians with opacity < `lod.opacity_threshold` are dropped: the
  threshold sets how many Gaussians (bytes) each layer adds (paper: "adjusting the opacity
  threshold ... to fine-tune transmitted rates").

Gaussians are stored layer by layer (layer 0 first), so layer k is a contiguous index range;
RUN/model.pt holds `layer` ([N] int32, each Gaussian's layer) and `lod` (levels, per-layer counts
and downscales). Checkpoints hold the per-layer counts, so a run resumes inside any layer.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from nehad.data.loader import load_dataset
from nehad.densify import append_gaussians, keep_gaussians
from nehad.splat.projection import quat_to_rotmat
from nehad.trainer import Trainer, _views


def layer_downscales(levels: int, downscale: int) -> list[int]:
    """Image downscale of each layer: layer 0 the coarsest, the last one `downscale`."""
    return [int(downscale) * 2 ** (levels - 1 - k) for k in range(levels)]


def layer_ids(layer_sizes) -> np.ndarray:
    """[N] int32 layer index of each Gaussian from the per-layer counts (layers contiguous)."""
    return np.repeat(np.arange(len(layer_sizes), dtype=np.int32),
                     np.asarray(layer_sizes, np.int64)).astype(np.int32)


class LodTrainer(Trainer):
    """`Trainer` with `cfg.lod.levels` layers (see the module doc). Same run directory layout,
    checkpoints and resume; `train()` writes RUN/model.pt with the layer of each Gaussian."""

    def __init__(self, cfg, data_dir, run_dir, resume: bool = False, progress: bool = True,
                 log=print):
        self._resumed_lod = None
        super().__init__(cfg, data_dir, run_dir, resume=resume, progress=progress, log=log)
        lod = cfg.lod
        self.levels = int(lod.levels)
        self.layer_iterations = int(lod.iterations or cfg.fine.iterations)
        if self.levels > 1 and self.layer_iterations < 1:
            from nehad.configtools import ConfigError

            raise ConfigError("lod.iterations: enhancement layers need >= 1 step (lod.iterations "
                              "and fine.iterations are both 0)")
        self.base_steps = cfg.coarse.iterations + cfg.fine.iterations
        self.total_steps = self.base_steps + (self.levels - 1) * self.layer_iterations
        self.downscales = layer_downscales(self.levels, cfg.data.downscale)
        self._layer_views = {self.levels - 1: self.train_views}  # loaded at data.downscale
        saved = self._resumed_lod or {}
        #: Gaussian counts of the finished (frozen) layers, in order.
        self.layer_sizes: list[int] = [int(v) for v in saved.get("layer_sizes", [])]
        self.strategy.frozen = sum(self.layer_sizes)
        self._apply_layer_cap(self.layer_of(self.step))
        self._snapshot = self._take_snapshot()
        self._current_step = self.step
        self.optimizer.register_step_pre_hook(self._zero_frozen_grads)
        self.optimizer.register_step_post_hook(self._restore_frozen)

    # -- schedule -----------------------------------------------------------------------------
    def layer_of(self, step: int) -> int:
        """The layer trained at (0-based) `step`."""
        if step < self.base_steps:
            return 0
        return min(1 + (step - self.base_steps) // self.layer_iterations, self.levels - 1)

    def layer_end(self, layer: int) -> int:
        """The number of steps done when `layer` is finished."""
        return self.base_steps + layer * self.layer_iterations

    def stage_of(self, step: int) -> tuple[str, int, int]:
        if step < self.base_steps:
            return super().stage_of(step)
        return "fine", (step - self.base_steps) % self.layer_iterations, self.layer_iterations

    def _set_learning_rates(self, stage: str, it: int, length: int) -> None:
        super()._set_learning_rates(stage, it, length)
        if self.layer_of(self._current_step) > 0 and not self.cfg.lod.train_field:
            for group in self.optimizer.param_groups:
                if group["name"] in ("grid", "decoder"):
                    group["lr"] = 0.0

    def time_window(self, stage: str, it: int, length: int):
        """Enhancement layers see every time: the time curriculum (nehad.curriculum) belongs to
        layer 0, where the shared field learns to follow the objects."""
        if self.layer_of(self._current_step) > 0:
            from nehad.curriculum import TimeWindow

            return TimeWindow(*self.scene.time_range)
        return super().time_window(stage, it, length)

    def resolution_factor(self, step: int) -> int:
        """Layer 0 follows data.resolution_schedule over its own steps; enhancement layers
        train at their layer's resolution throughout."""
        if self.layer_of(step) > 0:
            return 1
        return self.warmup_factor(step, self.base_steps)

    def views_of(self, layer: int):
        """Training views of `layer` at its resolution (loaded once)."""
        if layer not in self._layer_views:
            cfg = self.cfg
            bg = cfg.data.background if cfg.data.background is not None else (1.0, 1.0, 1.0)
            scene = load_dataset(self.data_dir, splits=(cfg.data.train_split,), background=bg,
                                 downscale=self.downscales[layer],
                                 frame_stride=cfg.data.frame_stride)
            self._layer_views[layer] = _views(scene, cfg.data.train_split)
        return self._layer_views[layer]

    def _apply_layer_cap(self, layer: int) -> None:
        """Densification cap of `layer`: `lod.base_max_gaussians` for layer 0 when set, else
        `densify.max_gaussians` (which counts only the trainable Gaussians, i.e. this layer's)."""
        base_cap = int(self.cfg.lod.base_max_gaussians)
        if layer == 0 and base_cap > 0:
            self.strategy.cfg = dataclasses.replace(self.cfg.densify, max_gaussians=base_cap)
        else:
            self.strategy.cfg = self.cfg.densify

    # -- freezing -----------------------------------------------------------------------------
    def _gaussian_groups(self):
        names = set(self.model.gaussians.NAMES)
        return [g for g in self.optimizer.param_groups if g["name"] in names]

    def _take_snapshot(self) -> dict:
        f = self.strategy.frozen
        g = self.model.gaussians
        return {name: getattr(g, name).detach()[:f].clone() for name in g.NAMES}

    def _zero_frozen_grads(self, optimizer, args, kwargs) -> None:
        f = self.strategy.frozen
        if f:
            for group in self._gaussian_groups():
                p = group["params"][0]
                if p.grad is not None:
                    p.grad[:f] = 0.0

    @torch.no_grad()
    def _restore_frozen(self, optimizer=None, args=None, kwargs=None) -> None:
        f = self.strategy.frozen
        if f:
            g = self.model.gaussians
            for name in g.NAMES:
                getattr(g, name)[:f] = self._snapshot[name]

    # -- layer boundaries ---------------------------------------------------------------------
    def start_fine_stage(self) -> None:
        layer = self.layer_of(self._current_step)
        if layer == 0:
            super().start_fine_stage()
        else:
            self._spawn_layer(layer)

    @torch.no_grad()
    def _spawn_layer(self, layer: int) -> None:
        """Seed layer `layer`: one child per frozen Gaussian (see the module doc)."""
        g = self.model.gaussians
        f = self.strategy.frozen
        gen = torch.Generator().manual_seed(int(self.cfg.train.seed) * 1_000_003 + 7919 * layer)
        scales = torch.exp(g.log_scales[:f])
        offsets = (quat_to_rotmat(g.quats[:f]) @ (torch.randn(scales.shape, generator=gen)
                                                  * scales)[..., None])[..., 0]
        new = {name: getattr(g, name)[:f].detach().clone() for name in g.NAMES}
        new["means"] = new["means"] + offsets
        new["log_scales"] = new["log_scales"] - math.log(2.0)
        p = float(self.cfg.lod.spawn_opacity)
        new["opacity_logits"] = torch.full_like(new["opacity_logits"], math.log(p / (1.0 - p)))
        append_gaussians(g, self.optimizer, new)
        self.strategy.reset(len(g))
        self._apply_layer_cap(layer)
        self.log_event(f"layer {layer}: {f} frozen Gaussians, {f} spawned, images at 1/"
                       f"{self.downscales[layer]}")

    @torch.no_grad()
    def _finish_layer(self, layer: int) -> None:
        """Drop the layer's Gaussians below the opacity threshold; freeze the rest."""
        g = self.model.gaussians
        f = self.strategy.frozen
        keep = torch.ones(len(g), dtype=torch.bool)
        opacity = torch.sigmoid(g.opacity_logits[f:].reshape(-1))
        keep[f:] = opacity >= self.cfg.lod.opacity_threshold
        if len(g) > f and not bool(keep[f:].any()):
            # a threshold above every opacity would leave an empty layer: keep it whole
            self._warn(f"warning: lod.opacity_threshold {self.cfg.lod.opacity_threshold:g} is above "
                     f"every opacity of layer {layer} (max {float(opacity.max()):.3g}); the "
                     f"layer is kept unthresholded")
            keep[f:] = True
        if not bool(keep.all()):
            keep_gaussians(g, self.optimizer, keep)
        self.layer_sizes.append(len(g) - f)
        self.strategy.frozen = len(g)
        self.strategy.reset(len(g))
        self._snapshot = self._take_snapshot()

    def log_event(self, text: str) -> None:
        if self.progress and self.log is not None:
            self.log(text)

    def _warn(self, text: str) -> None:
        if self.log is not None:
            self.log(text)

    # -- one step -----------------------------------------------------------------------------
    def train_step(self, step: int) -> dict:
        self._current_step = step
        layer = self.layer_of(step)
        self.train_views = self.views_of(layer)
        record = super().train_step(step)
        record["layer"] = layer
        if step + 1 == self.layer_end(layer):
            self._finish_layer(layer)
            record["layer_sizes"] = list(self.layer_sizes)
            record["gaussians"] = len(self.model.gaussians)
        return record

    # -- state ------------------------------------------------------------------------------
    def _build(self, state) -> None:
        self._resumed_lod = None if state is None else state.get("lod")
        super()._build(state)

    def lod_state(self) -> dict:
        return {"levels": self.levels, "layer_sizes": list(self.layer_sizes),
                "downscales": list(self.downscales), "iterations": self.layer_iterations,
                "opacity_threshold": float(self.cfg.lod.opacity_threshold)}

    def checkpoint_state(self) -> dict:
        state = super().checkpoint_state()
        state["lod"] = self.lod_state()
        return state

    def model_state(self) -> dict:
        state = super().model_state()
        sizes = list(self.layer_sizes)
        rest = len(self.model.gaussians) - sum(sizes)
        if rest:  # an unfinished layer (model_state of a run stopped early)
            sizes.append(rest)
        state["layer"] = torch.from_numpy(layer_ids(sizes))
        state["lod"] = {**self.lod_state(), "layer_sizes": sizes}
        return state


def make_trainer(cfg, data_dir, run_dir, resume: bool = False, progress: bool = True,
                 log=print) -> Trainer:
    """A `LodTrainer` when cfg.lod.levels > 1, else the ordinary `Trainer`."""
    cls = LodTrainer if cfg.lod.levels > 1 else Trainer
    return cls(cfg, data_dir, run_dir, resume=resume, progress=progress, log=log)


def run_layers(meta: dict, n: int) -> np.ndarray:
    """[n] int32 layer of each Gaussian of a loaded run (all 0 for a run without layers)."""
    layer = meta.get("layer")
    if layer is None:
        return np.zeros(n, np.int32)
    arr = np.asarray(layer.cpu().numpy() if torch.is_tensor(layer) else layer, np.int32)
    if arr.shape != (n,):
        raise ValueError(f"model.pt: 'layer' has shape {arr.shape}, expected ({n},)")
    return arr


__all__ = ["LodTrainer", "layer_downscales", "layer_ids", "make_trainer", "run_layers"]
