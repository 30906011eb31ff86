"""The NeHaD trainer (docs/training.md): one loop that follows a schedule object
(`nehad.schedule`: the static stage, then the deforming one; `nehad.lod.LayeredSchedule` adds
streaming layers) and two strategies beside it, 3DGS densification (`nehad.densify`) and
carving (`nehad.carve_pass`); Adam with per-parameter learning rates; 0.8 L1 + 0.2 D-SSIM, the
hex-plane regularisers and the priors on the motion; SH degree schedule; atomic checkpoints.

Determinism: the views and the split noise of step s are drawn from generators seeded by
(seed, s), so a run resumed from a checkpoint takes the same steps as one that never stopped.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from nehad.carve_pass import ResidualCarving, check_run_chains, free_offset_of, pin_mortal
from nehad.checkpoint import (RUN_FORMAT, append_metrics, atomic_torch_save, list_checkpoints,
                              load_state, prepare_run_dir, save_checkpoint)
from nehad.config import Config
from nehad.configtools import to_dict
from nehad.curriculum import eligible_frames, resolution_factor
from nehad.data.loader import load_dataset
from nehad.densify import DensifyState, DensifyStrategy, ViewStats
from nehad.field.deformation import DeformationField
from nehad.losses import view_loss
from nehad.lod import schedule_for
from nehad.model import NeHaDModel, RunError, model_from_state
from nehad.optim import make_optimizer, set_learning_rates
from nehad.runtime.interrupts import check as interrupt_point
from nehad.initial import initial_gaussians, scene_bounds
from nehad.motion_priors import MotionPriors
from nehad.schedule import Phase, Schedule
from nehad.splat.rasterize import render_torch
from nehad.views import (Views, downscale_views, recomposite, resolve_background, shown_psnr,
                         views_of)


class Trainer:
    """Trains a run folder from a dataset by `schedule` (default `nehad.lod.schedule_for`)."""

    def __init__(self, cfg: Config, data_dir, run_dir, resume: bool = False,
                 progress: bool = True, log=print, schedule: Schedule | None = None):
        self.cfg = cfg
        self.schedule = schedule_for(cfg) if schedule is None else schedule
        self.run, self.data_dir = Path(run_dir), Path(data_dir)
        self.progress, self.log = progress, log
        if resume and not (self.run / "config.yaml").exists():
            raise RunError(f"{self.run}: no run to resume (no config.yaml); leave out --resume "
                           f"to start one")
        torch.manual_seed(cfg.train.seed)
        # The dataset is read before anything is written, so a broken one leaves no run folder.
        # RGB images ignore the background, so one load over white (or the configured colour)
        # serves both kinds; the render background then follows from whether any frame has alpha
        load_bg = cfg.data.background if cfg.data.background is not None else (1.0, 1.0, 1.0)
        self.load_background = tuple(float(v) for v in load_bg)
        self.scene = load_dataset(self.data_dir, splits=(cfg.data.train_split,),
                                  background=load_bg, downscale=cfg.data.downscale,
                                  frame_stride=cfg.data.frame_stride)
        self.background = resolve_background(cfg.data.background, any(
            f.alpha is not None for f in self.scene.frames[cfg.data.train_split]))
        self.train_views = views_of(self.scene, cfg.data.train_split)
        self._scaled_views: dict = {}
        self.extent = float(self.scene.extent)
        self.aabb = scene_bounds(self.scene.initial_points)
        self.total_steps, self.step = self.schedule.total_steps, 0
        prepare_run_dir(self.run, cfg, resume)
        self._build(self._latest_checkpoint() if resume else None)

    # -- setup ---------------------------------------------------------------------------
    def _latest_checkpoint(self):
        ckpts = list_checkpoints(self.run)
        return load_state(ckpts[-1], resumable=True) if ckpts else None

    def _build(self, state) -> None:
        cfg = self.cfg
        if state is None:
            self.model = NeHaDModel(initial_gaussians(cfg.train, self.scene),
                                    DeformationField(cfg.field, torch.as_tensor(self.aabb),
                                                     self.extent))
            with torch.no_grad():  # a drift is measured from t_eq from the static stage on
                self.model.gaussians.t_eq.fill_(cfg.train.canonical_time)
            self.model.gaussians.drift_window = float(cfg.train.drift_window)
        else:  # a checkpoint: the one way a model is rebuilt from a saved state (drift window
            self.model = model_from_state(state).train()  # included)
        field = self.model.field
        self.optimizer = make_optimizer(self.model, cfg.optim, self.extent)
        self.strategy = DensifyStrategy(cfg.densify, self.extent)
        self.densify_state = DensifyState.zeros(0)
        self.priors = MotionPriors.of(cfg.loss, cfg.train.seed, self.train_views.times, cfg.carve,
                                      cfg.train.canonical_time, self.background)
        self.carving = ResidualCarving(cfg.carve, cfg.train.seed, cfg.train.canonical_time,
                                       cfg.densify.max_gaussians, self.aabb.copy(), self.background,
                                       free_offset_of(cfg.field, float(field.extent)))
        if state is not None:
            self.optimizer.load_state_dict(state["optimizer"])
            self.densify_state = DensifyState.from_state_dict(state["strategy"])
            self.step = int(state["step"])
            self.priors.load_state_dict(state)
        self.schedule.attach(self, state)
        self._enter_stage(self.schedule.phase(min(self.step, max(self.total_steps - 1, 0))))

    # -- what the schedule asks of the trainer ------------------------------------------
    def load_views(self, downscale: int) -> Views:
        """The training split at another image downscale (a streaming layer's)."""
        cfg = self.cfg
        return views_of(load_dataset(self.data_dir, splits=(cfg.data.train_split,),
                                     background=self.load_background, downscale=downscale,
                                     frame_stride=cfg.data.frame_stride), cfg.data.train_split)

    @property
    def layer_sizes(self) -> list[int]:  # of the finished streaming layers ([] without layers)
        return self.schedule.layer_sizes

    def log_event(self, text: str) -> None:  # a line about the run's progress, with the bar
        if self.progress and self.log is not None:
            self.log(text)

    def warn(self, text: str) -> None:
        if self.log is not None:
            self.log(text)

    # -- what the schedule decides ------------------------------------------------------
    def _enter_stage(self, phase: Phase) -> None:
        """The densification timing of the phase's stage (nehad.densify)."""
        self.densify_timing = self.strategy.timing(self.schedule.stage_config(phase), phase.length)
        self._phase_key = phase.key

    def views_at(self, step: int, phase: Phase | None = None) -> Views:
        """The training views of `step`: its layer's, at its point of the resolution warm-up
        (data.resolution_schedule, limited by data.warmup_min_size)."""
        phase = self.schedule.phase(step) if phase is None else phase
        views = self.schedule.views(self, phase.layer)
        warmup = self.schedule.resolution_warmup(step, phase)
        if warmup is None or not views.images:
            return views
        short_side = min(views.images[0].shape[0], views.images[0].shape[1])
        factor = resolution_factor(self.cfg.data.resolution_schedule, *warmup, short_side,
                                   self.cfg.data.warmup_min_size)
        if factor == 1:
            return views
        key = (id(views), factor)
        if key not in self._scaled_views:
            self._scaled_views[key] = downscale_views(views, factor)
        return self._scaled_views[key]

    def active_sh_degree(self, step: int) -> int:
        return min(self.cfg.train.sh_degree, step // max(self.cfg.train.sh_degree_interval, 1))

    # -- one step --------------------------------------------------------------------------
    def train_step(self, step: int) -> dict:
        """One optimisation step: enter the phase, draw views, render and score them, update,
        then let the strategies change the model."""
        phase = self._begin_phase(step)
        window = self.schedule.time_window(self, phase)
        views = self.views_at(step, phase)
        rng = np.random.default_rng([self.cfg.train.seed, step])
        picks = self._pick_views(phase, views, window, rng)
        with self.model.field.hexplane.adding_gradients_in_place():
            scored = self._render_loss(phase, step, views, picks, rng, self.logs_step(step))
        total, psnrs, renders = scored
        self._update(total, phase, window)
        did = self._change_model(phase, step, window, renders)
        record = {"step": step + 1, "stage": phase.stage, "loss": float(total.item()),
                  "psnr": float(np.mean(psnrs)) if psnrs else None,  # logged steps only
                  "gaussians": len(self.model.gaussians), "sh_degree": self.active_sh_degree(step),
                  "window": [round(window.lo, 4), round(window.hi, 4)],
                  "resolution": list(renders[-1][0].rgb.shape[1::-1]),
                  **{k: v for k, v in did.items() if k != "gaussians"}}
        self.schedule.end(self, phase, step, record)
        return record

    def _begin_phase(self, step: int) -> Phase:
        phase = self.schedule.phase(step)
        if phase.it == 0 or phase.key != self._phase_key:
            self._enter_stage(phase)
        if phase.it == 0:
            self.schedule.begin(self, phase)  # a stage's or layer's first step
        set_learning_rates(self.optimizer, self.cfg.optim, self.extent, phase,
                           self.schedule.frozen_groups(phase))
        return phase

    def _pick_views(self, phase: Phase, views: Views, window, rng) -> np.ndarray:
        batch = self.schedule.stage_config(phase).batch_size
        pool = eligible_frames(views.times, window)
        return rng.choice(pool, size=batch, replace=batch > len(pool))

    def logs_step(self, step: int) -> bool:
        """Whether step `step` (0-based) is one `train` writes to metrics.jsonl and the bar."""
        return (step + 1) % self.cfg.train.log_interval == 0 or step + 1 == self.total_steps

    def _render_loss(self, phase: Phase, step: int, views: Views, picks, rng, score: bool):
        """(the step's loss, each view's PSNR if `score` (a logged step; 2% of a demo step),
        (render, camera) per view)."""
        cfg = self.cfg
        degree = self.active_sh_degree(step)
        total, psnrs, renders = 0.0, [], []
        for k in picks:
            cam, target, alpha = views.cameras[k], views.images[k], views.alphas[k]
            params, sampled = self.priors.gaussians_at(self.model, views.times[k], step,
                                                       phase.deforms)
            background = self.background
            if cfg.data.random_background and alpha is not None:
                background = tuple(float(v) for v in rng.random(3))
                target = recomposite(target, alpha, self.load_background, background)
            res = render_torch(*params, cam, background=background, sh_degree=degree)
            progress = phase.it / max(phase.length, 1) if phase.deforms else None
            total = total + view_loss(res.rgb, target, cfg.loss, progress) / len(picks)
            if phase.deforms:  # the priors on the motion (nehad.motion_priors)
                prior = self.priors.loss(self.model, params[0], views.times[k], step, sampled)
                total = total + prior / len(picks)
            renders.append((res, cam))
            if score:  # logged against the evaluation background, whatever the step trained over
                psnrs.append(shown_psnr(res, target, alpha, background, self.background))
        if phase.deforms:
            total = total + self.model.field.regularization_loss()
        if not torch.isfinite(total):
            raise RunError(f"step {step + 1}: the loss became {float(total.detach())}; training "
                           f"stopped (the last checkpoint in {self.run} is intact)")
        return total, psnrs, renders

    def _update(self, total, phase: Phase, window) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        if self.cfg.carve.pin:
            pin_mortal(self.model.gaussians)
        self.schedule.before_update(self)
        self.optimizer.step()
        self.schedule.after_update(self, phase, window)

    def _change_model(self, phase: Phase, step: int, window, renders) -> dict:
        """Densification, then carving (the strategies); a warning when the model empties."""
        stats = [ViewStats(res.means2d.grad, res.radii, cam.width, cam.height)
                 for res, cam in renders]
        gen = torch.Generator().manual_seed(int(self.cfg.train.seed) * 1_000_003 + step)
        frozen, cap = self.schedule.densify_limits(phase)
        did = self.strategy.step_post_backward(
            self.model.gaussians, self.optimizer, self.densify_state, phase.it + 1,
            self.densify_timing, stats, frozen=frozen, max_gaussians=cap, generator=gen)
        # carving sees the layer's own resolution, not the warm-up's (docs/training.md)
        did.update(self.carving.step_post_update(
            self.model, self.optimizer, self.densify_state, deforms=phase.deforms,
            layer=phase.layer, it=phase.it + 1, step=step, window=window,
            views=self.schedule.views(self, phase.layer),
            degree=self.active_sh_degree(step), timing=self.densify_timing,
            priors=self.priors))
        if len(self.model.gaussians) == 0 and not getattr(self, "_warned_empty", False):
            self._warned_empty = True  # the stress suite's thin rod: docs/results.md
            self.warn(f"warning: step {step + 1}: every Gaussian was pruned; the model now draws "
                      f"only the background (objects too small or too fast, docs/training.md)")
        return did

    # -- loop ----------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        return {"step": self.step, "gaussians": self.model.gaussians.state_dict(),
                "field": self.model.field.state_dict(), "optimizer": self.optimizer.state_dict(),
                "strategy": self.densify_state.state_dict(), "config": to_dict(self.cfg),
                **self.priors.state_dict(), **self.schedule.state_dict()}

    def model_state(self) -> dict:
        """RUN/model.pt (read back as `nehad.model.load_run`'s model and RunInfo)."""
        return {"format": RUN_FORMAT, "gaussians": self.model.gaussians.state_dict(),
                "field": self.model.field.state_dict(), "config": to_dict(self.cfg),
                "aabb": torch.as_tensor(self.aabb), "extent": self.extent,
                "background": list(self.background),
                "sh_degree": self.active_sh_degree(self.total_steps),
                "time_range": list(self.scene.time_range), "steps": self.step,
                "data_dir": str(self.data_dir.resolve()), **self.schedule.model_extras(self)}

    def train(self) -> dict:
        from tqdm import tqdm

        cfg = self.cfg
        start_time = time.perf_counter()
        bar = tqdm(total=self.total_steps, initial=self.step, disable=not self.progress,
                   dynamic_ncols=True, desc="train")
        record = {}
        while self.step < self.total_steps:
            interrupt_point()  # a waiting Ctrl-C is raised here, between steps (issue 26)
            record = self.train_step(self.step)
            self.step += 1
            bar.update(1)
            if self.logs_step(self.step - 1):
                record["seconds"] = round(time.perf_counter() - start_time, 2)
                append_metrics(self.run, record)
                bar.set_postfix(stage=record["stage"], loss=f"{record['loss']:.4f}",
                                psnr=f"{record['psnr']:.2f}", n=record["gaussians"])
            if (self.step % cfg.train.checkpoint_interval == 0
                    or self.schedule.ends_stage(self.step)):
                save_checkpoint(self.run, self.step, self.checkpoint_state(),
                                cfg.train.keep_checkpoints)
        bar.close()
        checked = check_run_chains(self.carving, self.model, self.cfg, self.data_dir, self.run,
                                   self.step, self.load_background, self.train_views,
                                   self.active_sh_degree(max(self.step - 1, 0)))
        atomic_torch_save(self.model_state(), self.run / "model.pt")
        return {"steps": self.step, "gaussians": len(self.model.gaussians),
                "seconds": time.perf_counter() - start_time, "last": record, **checked}
