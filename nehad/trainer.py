"""The NeHaD trainer (docs/training.md): one loop that follows a schedule object
(`nehad.schedule`: the coarse stage of static 3DGS, then the fine stage with the deformation field
on; `nehad.lod.LayeredSchedule` adds streaming layers); Adam with per-parameter learning rates and
exponential schedules; the 3DGS densification strategy (`nehad.densify`); 0.8 L1 + 0.2 D-SSIM
plus the hex-plane regularisers; SH degree schedule; atomic checkpoints and exact resume.

Determinism: the views of step s are drawn from a generator seeded by (seed, s) and the split
noise of step s likewise, so a run resumed from a checkpoint takes the same steps as one that
never stopped.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nehad.checkpoint import (append_metrics, atomic_torch_save, list_checkpoints, load_state,
                              save_checkpoint)
from nehad.config import Config
from nehad.configtools import ConfigError, diff, dump_yaml, to_dict
from nehad.data.common import DNeRFScene
from nehad.data.loader import load_dataset
from nehad.curriculum import eligible_frames, hold_time_planes, resolution_factor
from nehad.densify import DensifySchedule, DensifyStrategy
from nehad.field.deformation import DeformationField
from nehad.gaussians import GaussianParameters
from nehad.losses import photometric_loss, psnr
from nehad.runtime.interrupts import check as interrupt_point
from nehad.lod import schedule_for
from nehad.model import NeHaDModel, RunError, cloud_at
from nehad.schedule import Phase, Schedule
from nehad.splat.rasterize import render_torch


def resolve_background(cfg: Config, scene_has_alpha: bool) -> tuple[float, float, float]:
    if cfg.data.background is not None:
        return tuple(float(v) for v in cfg.data.background)
    return (1.0, 1.0, 1.0) if scene_has_alpha else (0.0, 0.0, 0.0)


def exp_lr(step: int, total: int, lr_init: float, lr_final: float) -> float:
    """Log-linear interpolation from lr_init to lr_final over `total` steps (3DGS schedule)."""
    if total <= 0 or lr_init <= 0:
        return lr_init
    t = min(max(step / total, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(max(lr_final, 1e-30)) * t)


@dataclass
class Views:
    cameras: list
    images: list  # (H, W, 3) float32 tensors, composited over the load background
    times: list
    alphas: list  # (H, W, 1) float32 tensors, or None for images without alpha


def _views(scene: DNeRFScene, split: str) -> Views:
    frames = scene.frames[split]
    return Views([f.camera for f in frames], [torch.from_numpy(np.ascontiguousarray(f.image))
                                              for f in frames],
                 [float(f.camera.time or 0.0) for f in frames],
                 [None if f.alpha is None else torch.from_numpy(f.alpha)[:, :, None]
                  for f in frames])


def _downscale_views(views: Views, factor: int) -> Views:
    """`views` area-downscaled by an integer factor (a remainder at the right/bottom edge is
    cropped, as the dataset readers crop it), cameras to match."""
    def pool(img):
        h, w, c = img.shape
        h2, w2 = h // factor, w // factor
        return img[:h2 * factor, :w2 * factor].reshape(h2, factor, w2, factor, c).mean((1, 3))

    cams = [dataclasses.replace(c, width=c.width // factor, height=c.height // factor,
                                fx=c.fx / factor, fy=c.fy / factor, cx=c.cx / factor,
                                cy=c.cy / factor) for c in views.cameras]
    return Views(cams, [pool(im).contiguous() for im in views.images], list(views.times),
                 [None if a is None else pool(a).contiguous() for a in views.alphas])


def recomposite(image: torch.Tensor, alpha: torch.Tensor, old_bg, new_bg) -> torch.Tensor:
    """An image composited over `old_bg`, composited over `new_bg` instead:
    rgb + (new - old)(1 - a) (the loader adds bg (1 - a) to premultiplied colour)."""
    delta = torch.as_tensor(np.asarray(new_bg, np.float32) - np.asarray(old_bg, np.float32))
    return image + delta * (1.0 - alpha)


def scene_bounds(points: np.ndarray | None) -> np.ndarray:
    """The hex-plane's aabb (2, 3): the initial points' bounds (4DGS), else [-1.3, 1.3]^3."""
    if points is None or len(points) == 0:
        return np.array([[-1.3] * 3, [1.3] * 3], np.float32)
    lo, hi = points.min(0), points.max(0)
    pad = 0.05 * (hi - lo).max()
    return np.stack([lo - pad, hi + pad]).astype(np.float32)


class Trainer:
    """Trains a run directory from a dataset, following `schedule` (default: the one `cfg` asks
    for, `nehad.lod.schedule_for`); see `make_trainer`."""

    def __init__(self, cfg: Config, data_dir, run_dir, resume: bool = False,
                 progress: bool = True, log=print, schedule: Schedule | None = None):
        self.cfg = cfg
        self.schedule = schedule_for(cfg) if schedule is None else schedule
        self.run = Path(run_dir)
        self.data_dir = Path(data_dir)
        self.progress = progress
        self.log = log
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
        has_alpha = any(f.alpha is not None for f in self.scene.frames[cfg.data.train_split])
        self.background = resolve_background(cfg, has_alpha)
        self.train_views = _views(self.scene, cfg.data.train_split)
        self._scaled_views: dict = {}
        self.extent = float(self.scene.extent)
        self.aabb = scene_bounds(self.scene.initial_points)
        self.carve_box = self.aabb.copy()  # residual carving samples depths in it (nehad.carve)
        self.total_steps = self.schedule.total_steps
        self.step = 0
        self._check_run_dir(resume)
        state = self._latest_checkpoint() if resume else None
        self._build(state)

    # -- setup ---------------------------------------------------------------------------
    def _check_run_dir(self, resume: bool) -> None:
        cfg_path = self.run / "config.yaml"
        if cfg_path.exists():
            from nehad.configtools import load_yaml
            saved = load_yaml(cfg_path)  # a damaged config.yaml: one error naming it (issue 26)
            if not resume:
                raise RunError(f"{self.run}: already holds a run; pass --resume to continue it "
                               f"or choose another output folder")
            changes = diff(saved, to_dict(self.cfg))
            if changes:
                raise RunError(f"{self.run}: --resume with a different config than the run's "
                               f"({'; '.join(changes[:6])}); use the same preset/--set values "
                               f"or another output folder")
        self.run.mkdir(parents=True, exist_ok=True)
        if not cfg_path.exists():
            from nehad.runtime.images import atomic_write_bytes
            atomic_write_bytes(cfg_path, dump_yaml(self.cfg).encode())

    def _latest_checkpoint(self):
        ckpts = list_checkpoints(self.run)
        return load_state(ckpts[-1]) if ckpts else None

    def _init_gaussians(self) -> GaussianParameters:
        cfg = self.cfg.train
        pts = self.scene.initial_points
        use_points = cfg.init == "points" or (cfg.init == "auto" and pts is not None)
        if use_points:
            if pts is None:
                raise ConfigError("train.init: 'points' but the dataset has no point cloud")
            colors = self.scene.initial_colors
            if 0 < cfg.init_max_points < len(pts):
                keep = np.random.default_rng(cfg.seed).choice(len(pts), cfg.init_max_points,
                                                              replace=False)
                pts = pts[keep]
                colors = None if colors is None else colors[keep]
            return GaussianParameters.from_points(pts, colors, sh_degree=cfg.sh_degree,
                                                  seed=cfg.seed)
        return GaussianParameters.random_in_box(cfg.init_random_points, sh_degree=cfg.sh_degree,
                                                seed=cfg.seed)

    def _build(self, state) -> None:
        cfg = self.cfg
        if state is None:
            gaussians = self._init_gaussians()
        else:
            gaussians = GaussianParameters.empty_like_state(state["gaussians"])
            gaussians.load_state_dict(state["gaussians"])
        field = DeformationField(cfg.field, torch.as_tensor(self.aabb), self.extent)
        if state is not None:
            field.load_state_dict(state["field"])
        self.model = NeHaDModel(gaussians, field)
        self.optimizer = self._make_optimizer()
        self.strategy = DensifyStrategy(cfg.densify, self.extent)
        if state is not None:
            self.optimizer.load_state_dict(state["optimizer"])
            self.strategy.load_state_dict(state["strategy"])
            self.step = int(state["step"])
        self.schedule.attach(self, state)
        self._enter_stage(self.schedule.phase(min(self.step, max(self.total_steps - 1, 0))))

    def _make_optimizer(self) -> torch.optim.Optimizer:
        o, g = self.cfg.optim, self.model.gaussians
        groups = [
            {"name": "means", "params": [g.means], "lr": o.position_lr_init * self.extent},
            {"name": "sh_dc", "params": [g.sh_dc], "lr": o.sh_dc_lr},
            {"name": "sh_rest", "params": [g.sh_rest], "lr": o.sh_dc_lr / o.sh_rest_lr_divisor},
            {"name": "opacity_logits", "params": [g.opacity_logits], "lr": o.opacity_lr},
            {"name": "log_scales", "params": [g.log_scales], "lr": o.scaling_lr},
            {"name": "quats", "params": [g.quats], "lr": o.rotation_lr},
            {"name": "mu_eq", "params": [g.mu_eq], "lr": 0.0},
            {"name": "t_eq", "params": [g.t_eq], "lr": 0.0},
            {"name": "life_rate", "params": [g.life_rate], "lr": o.life_rate_lr},
            {"name": "velocity", "params": [g.velocity], "lr": o.velocity_lr * self.extent},
        ]
        field_groups = self.model.field.param_groups()
        groups.append({"name": "grid", "params": list(field_groups["grid"]), "lr": 0.0})
        groups.append({"name": "decoder", "params": list(field_groups["decoder"]), "lr": 0.0})
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    # -- what the schedule asks of the trainer ------------------------------------------
    def load_views(self, downscale: int) -> Views:
        """The training split at another image downscale (a streaming layer's)."""
        cfg = self.cfg
        scene = load_dataset(self.data_dir, splits=(cfg.data.train_split,),
                             background=self.load_background, downscale=downscale,
                             frame_stride=cfg.data.frame_stride)
        return _views(scene, cfg.data.train_split)

    @property
    def layer_sizes(self) -> list[int]:
        """Gaussian counts of the finished streaming layers ([] without layers)."""
        return self.schedule.layer_sizes

    def log_event(self, text: str) -> None:
        """A line about the run's progress (shown with the progress bar)."""
        if self.progress and self.log is not None:
            self.log(text)

    def warn(self, text: str) -> None:
        if self.log is not None:
            self.log(text)

    # -- what the schedule decides ------------------------------------------------------
    def _set_learning_rates(self, phase: Phase) -> None:
        """Exponential decays over the stage (layer); the groups the schedule freezes get 0."""
        o = self.cfg.optim
        it, length = phase.it, phase.length
        frozen = self.schedule.frozen_groups(phase)
        for group in self.optimizer.param_groups:
            name = group["name"]
            if name in ("means", "mu_eq"):
                lr = exp_lr(it, length, o.position_lr_init, o.position_lr_final) * self.extent
            elif name == "t_eq":
                lr = o.t_eq_lr
            elif name == "grid":
                lr = exp_lr(it, length, o.grid_lr_init, o.grid_lr_final)
            elif name == "decoder":
                final = o.decoder_lr if o.decoder_lr_final is None else o.decoder_lr_final
                lr = exp_lr(it, length, o.decoder_lr, final)
            else:
                continue  # constant learning rates
            group["lr"] = 0.0 if name in frozen else lr

    def _enter_stage(self, phase: Phase) -> None:
        """Give the densification strategy the schedule of the phase's stage (nehad.densify)."""
        self.strategy.schedule = DensifySchedule.for_stage(self.schedule.stage_config(phase),
                                                           phase.length,
                                                           self.cfg.densify.interval)
        self._phase_key = phase.key

    def warmup_factor(self, views: Views, step: int, total: int) -> int:
        """data.resolution_schedule at `step` of `total` for `views`, limited by
        data.warmup_min_size."""
        image = views.images[0] if views.images else None
        short_side = None if image is None else min(image.shape[0], image.shape[1])
        return resolution_factor(self.cfg.data.resolution_schedule, step, total, short_side,
                                 self.cfg.data.warmup_min_size)

    def views_at(self, step: int, phase: Phase | None = None) -> Views:
        """The training views of `step`: its layer's, at its point of the resolution warm-up."""
        phase = self.schedule.phase(step) if phase is None else phase
        views = self.schedule.views(self, phase.layer)
        warmup = self.schedule.resolution_warmup(step, phase)
        factor = 1 if warmup is None else self.warmup_factor(views, *warmup)
        if factor == 1:
            return views
        key = (id(views), factor)
        if key not in self._scaled_views:
            self._scaled_views[key] = _downscale_views(views, factor)
        return self._scaled_views[key]

    def active_sh_degree(self, step: int) -> int:
        return min(self.cfg.train.sh_degree, step // max(self.cfg.train.sh_degree_interval, 1))

    # -- one step --------------------------------------------------------------------------
    def train_step(self, step: int) -> dict:
        cfg, schedule = self.cfg, self.schedule
        phase = schedule.phase(step)
        if phase.it == 0 or phase.key != self._phase_key:
            self._enter_stage(phase)
        if phase.it == 0:
            schedule.begin(self, phase)  # a stage's or layer's first step
        self._set_learning_rates(phase)
        batch = schedule.stage_config(phase).batch_size
        window = schedule.time_window(self, phase)
        views = self.views_at(step, phase)
        rng = np.random.default_rng([cfg.train.seed, step])
        pool = eligible_frames(views.times, window)
        picks = rng.choice(pool, size=batch, replace=batch > len(pool))
        degree = self.active_sh_degree(step)
        total = 0.0
        psnrs = []
        renders = []
        for k in picks:
            cam = views.cameras[k]
            params = self.model.gaussians_at(views.times[k], deform=phase.deforms)
            target, alpha = views.images[k], views.alphas[k]
            background = self.background
            if cfg.data.random_background and alpha is not None:
                background = tuple(float(v) for v in rng.random(3))
                target = recomposite(target, alpha, self.load_background, background)
            res = render_torch(*params, cam, background=background, sh_degree=degree)
            loss = photometric_loss(res.rgb, target, cfg.loss.ssim_weight,
                                    cfg.loss.kernel) / batch
            total = total + loss
            # logged against the evaluation background, whatever the step trained over
            psnrs.append(psnr(recomposite(res.rgb.detach(), res.alpha.detach()[:, :, None],
                                          background, self.background),
                              recomposite(target, alpha, background, self.background)
                              if alpha is not None and background != self.background
                              else target))
            renders.append((res, cam))
        if phase.deforms:
            total = total + self.model.field.regularization_loss()
        if not torch.isfinite(total):
            raise RunError(f"step {step + 1}: the loss became {float(total)}; training stopped "
                           f"(the last checkpoint in {self.run} is intact)")
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        for res, cam in renders:
            self.strategy.record_view(res.means2d.grad, res.radii, cam.width, cam.height)
        schedule.before_update(self)
        self.optimizer.step()
        schedule.after_update(self)
        if phase.deforms and cfg.train.hold_time_planes:
            full = window.lo <= self.scene.time_range[0] and window.hi >= self.scene.time_range[1]
            if not full:
                hold_time_planes(self.model.field.hexplane, window)
        gen = torch.Generator().manual_seed(int(cfg.train.seed) * 1_000_003 + step)
        did = self.strategy.step_post_backward(self.model.gaussians, self.optimizer, phase.it + 1,
                                               gen)
        did.update(self._carve_if_due(phase, step, window, views))
        if len(self.model.gaussians) == 0 and not getattr(self, "_warned_empty", False):
            self._warned_empty = True  # the stress suite's thin rod: docs/results.md
            self.warn(f"warning: step {step + 1}: every Gaussian was pruned; the model now "
                      f"draws only the background (objects too small or too fast for the "
                      f"recipe, docs/training.md)")
        record = {"step": step + 1, "stage": phase.stage, "loss": float(total.item()),
                  "psnr": float(np.mean(psnrs)), "gaussians": len(self.model.gaussians),
                  "sh_degree": degree, "window": [round(window.lo, 4), round(window.hi, 4)],
                  "resolution": list(res.rgb.shape[1::-1]),
                  **{k: v for k, v in did.items() if k != "gaussians"}}
        schedule.end(self, phase, step, record)
        return record

    def free_offset(self) -> float:
        """A distance from a Gaussian to its equilibrium at which the BED position mask is at
        its floor gamma to float32 precision (dd = 12 sigma_s: exp(-72) ~ 1e-31)."""
        return 12.0 * self.cfg.field.sigma_s_fraction * float(self.model.field.extent)

    def _carve_if_due(self, phase: Phase, step: int, window, views: Views) -> dict:
        """A residual carving pass (nehad.carve) every carve.every iterations of the stage's
        densification window: the carve.views frames (carve.mode=rays: carve.seed_views) of the
        time window nearest to one time (the canonical time in the coarse stage; in the fine
        stage the frame time nearest to the next point of a van der Corput sequence over the
        window, so that successive passes cover the time range evenly), each rendered at its
        own time."""
        from nehad.carve import carve_points, new_gaussians, seed_rays
        from nehad.densify import append_gaussians, keep_gaussians
        from nehad.runtime.raster import render

        c = self.cfg.carve
        sched = self.strategy.schedule
        it = phase.it + 1
        if (c.every <= 0 or c.max_new <= 0 or phase.layer > 0 or self.strategy.frozen
                or (not phase.deforms and not c.static_stage)
                or not sched.start <= it < sched.stop or it % c.every or sched.recovering(it)):
            return {}
        rng = np.random.default_rng([self.cfg.train.seed, step, 7])
        pool = eligible_frames(views.times, window)
        times = np.asarray(views.times, np.float64)
        if phase.deforms:  # the passes' times spread evenly over the window (van der Corput)
            at = window.lo + (window.hi - window.lo) * van_der_corput(it // c.every)
            t_c = float(times[pool[np.argmin(np.abs(times[pool] - at))]])
        else:
            t_c = float(self.cfg.train.canonical_time)
        count = c.seed_views if c.mode == "rays" else c.views
        nearest = pool[np.argsort(np.abs(times[pool] - t_c), kind="stable")[:count]]
        degree = self.active_sh_degree(step)
        cams, targets, alphas, drawn = [], [], [], []
        canonical = None if phase.deforms else cloud_at(self.model, None, degree)
        for k in nearest:
            cloud = canonical if canonical is not None else cloud_at(self.model, times[k], degree)
            cams.append(views.cameras[k])
            drawn.append(render(cloud, views.cameras[k], self.background))
            targets.append(views.images[k].numpy())
            a = views.alphas[k]
            alphas.append(None if a is None else a.numpy()[:, :, 0])
        if c.mode == "rays":
            pts, cols, widths, n_bad = seed_rays(
                cams, targets, alphas, [d.rgb for d in drawn], self.carve_box,
                residual=c.residual, stride=c.stride, depth_samples=c.depth_samples, rng=rng)
        else:
            pts, cols, widths, n_bad = carve_points(
                cams, targets, alphas, [d.rgb for d in drawn], self.carve_box, times[nearest],
                render_alphas=[d.alpha for d in drawn], render_depths=[d.depth for d in drawn],
                residual=c.residual, stride=c.stride, depth_samples=c.depth_samples,
                min_views=c.min_views, agree=c.agree, colour_tol=c.colour_tol,
                motion=c.motion, rng=rng)
        cap = self.cfg.densify.max_gaussians
        most = min(c.max_new, cap) if cap > 0 else c.max_new  # a pass never overfills the cap
        if len(pts) > most:
            pick = rng.choice(len(pts), most, replace=False)
            pts, cols, widths = pts[pick], cols[pick], widths[pick]
        out = {"carve_time": round(t_c, 4), "carve_unexplained": n_bad, "carved": len(pts)}
        if not len(pts):
            return out
        g = self.model.gaussians
        over = len(g) + len(pts) - cap if cap > 0 else 0
        keep = torch.ones(len(g), dtype=torch.bool)
        if over > 0:  # relocate: the least opaque Gaussians make room (nehad.carve)
            keep[torch.argsort(g.opacity_logits.detach().reshape(-1))[:min(over, len(g))]] = False
            keep_gaussians(g, self.optimizer, keep)
            out["relocated"] = int((~keep).sum())
        spacing = float(np.median(np.diff(np.unique(times)))) if len(np.unique(times)) > 1 else 0.0
        life = c.life * spacing if phase.deforms else 0.0
        append_gaussians(g, self.optimizer,
                         new_gaussians(pts, cols, widths, t_c, g, c.opacity, life,
                                       0.0 if c.hold else self.free_offset()))
        if self.strategy.state.grad_accum.shape[0] == len(keep):  # statistics follow
            self.strategy.state = self.strategy.state.kept(keep, len(pts))
        return out

    # -- loop ----------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        return {"step": self.step, "gaussians": self.model.gaussians.state_dict(),
                "field": self.model.field.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "strategy": self.strategy.state_dict(), "config": to_dict(self.cfg),
                **self.schedule.state_dict()}

    def model_state(self) -> dict:
        return {"format": "nehad-run/1", "gaussians": self.model.gaussians.state_dict(),
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
            if self.step % cfg.train.log_interval == 0 or self.step == self.total_steps:
                record["seconds"] = round(time.perf_counter() - start_time, 2)
                append_metrics(self.run, record)
                bar.set_postfix(stage=record["stage"], loss=f"{record['loss']:.4f}",
                                psnr=f"{record['psnr']:.2f}", n=record["gaussians"])
            stage_end = self.step == cfg.coarse.iterations or self.step == self.total_steps
            if self.step % cfg.train.checkpoint_interval == 0 or stage_end:
                save_checkpoint(self.run, self.step, self.checkpoint_state(),
                                cfg.train.keep_checkpoints)
        bar.close()
        atomic_torch_save(self.model_state(), self.run / "model.pt")
        return {"steps": self.step, "gaussians": len(self.model.gaussians),
                "seconds": time.perf_counter() - start_time, "last": record}


def make_trainer(cfg: Config, data_dir, run_dir, resume: bool = False, progress: bool = True,
                 log=print) -> Trainer:
    """The trainer `nehad train`, `nehad demo` and bench/quality.py run: the schedule follows
    from `cfg` (coarse + fine stages; streaming layers when lod.levels > 1)."""
    return Trainer(cfg, data_dir, run_dir, resume=resume, progress=progress, log=log,
                   schedule=schedule_for(cfg))


def van_der_corput(i: int) -> float:
    """The i-th point (i >= 1) of the base-2 van der Corput sequence in [0, 1): 0.5, 0.25,
    0.75, 0.125, ...; any run of consecutive points spreads evenly over [0, 1)."""
    x, f = 0.0, 0.5
    while i > 0:
        x += f * (i & 1)
        i >>= 1
        f *= 0.5
    return x
