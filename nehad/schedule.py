"""Training schedules: what each step of the trainer trains (docs/training.md,
docs/streaming.md).

`nehad.trainer.Trainer` is one loop. Everything that depends on where a step falls in the run is
answered by the schedule object it holds, as `nehad.densify.DensifyStrategy` answers when to
clone, split and prune (gsplat's layout: strategy objects beside a small loop). Per step the
trainer asks:

* `phase(step)`: the stage ("coarse": static Gaussians; "fine": the deformation field on), the
  streaming layer, the iteration within them and their length (a `Phase`);
* `stage_config(phase)`: the StageConfig of the phase (batch size, densification fractions);
* `views(trainer, layer)` and `resolution_warmup(step, phase)`: which images, and where the step
  falls in `data.resolution_schedule` (the trainer turns that into a downscale factor);
* `time_window(trainer, phase)`: the times the step may draw frames from (the time curriculum,
  `nehad.curriculum`);
* `frozen_groups(phase)`: the optimizer groups that do not learn in the phase;
* `densify_limits(phase)`: (the number of leading Gaussians densification must leave alone, the
  Gaussian cap), which the trainer passes to the densification strategy;
* `begin(trainer, phase)`: what happens at the first step of a stage or layer;
* `before_update(trainer)` / `after_update(trainer, phase, window)`: around Adam's step (frozen
  layers; the time curriculum's held hex-plane rows);
* `end(trainer, phase, step, record)`: after the step (a layer's end);
* `ends_stage(steps_done)`: whether a checkpoint is due because a stage just ended;

and, for the run as a whole, `total_steps`, `layer_sizes`, `attach(trainer, state)` (after the
model is built or loaded from a checkpoint), `state_dict()` (what a checkpoint holds beyond the
trainer's state) and `model_extras(trainer)` (what RUN/model.pt holds beyond it).

`StagedSchedule` is the ordinary run: the coarse stage, then the fine stage. With
`fine.iterations=0` it is a static 3DGS fit. `nehad.lod.LayeredSchedule` trains streaming layers
on top of it. `nehad.lod.schedule_for(cfg)` picks one from the config, so every way of building a trainer
(`nehad train`, `nehad demo`, bench/quality.py, `Trainer(cfg, ...)`) trains the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from nehad.curriculum import TimeWindow, hold_time_planes, widen_to_frames, window_at

if TYPE_CHECKING:
    from nehad.config import Config, StageConfig
    from nehad.gaussians import GaussianParameters
    from nehad.trainer import Trainer, Views


@dataclass(frozen=True)
class Phase:
    """Where one step falls in the run."""

    stage: str  # "coarse" (static Gaussians) or "fine" (the deformation field on)
    it: int  # 0-based iteration within the stage (an enhancement layer: within the layer)
    length: int  # the stage's (layer's) number of iterations
    layer: int = 0  # streaming layer (0 without layers)

    @property
    def deforms(self) -> bool:
        """The step renders the deformed Gaussians and adds the field's regularisers."""
        return self.stage == "fine"

    @property
    def key(self) -> tuple:
        """Equal for every step of one stage (or layer)."""
        return self.stage, self.layer, self.length


class Schedule(Protocol):
    """What the trainer asks its schedule (see the module doc)."""

    total_steps: int
    layer_sizes: list[int]  # Gaussian counts of the finished (frozen) layers; [] without layers

    def phase(self, step: int) -> Phase: ...

    def stage_config(self, phase: Phase) -> StageConfig: ...

    def views(self, trainer: Trainer, layer: int) -> Views: ...

    def resolution_warmup(self, step: int, phase: Phase) -> tuple[int, int] | None: ...

    def time_window(self, trainer: Trainer, phase: Phase) -> TimeWindow: ...

    def frozen_groups(self, phase: Phase) -> frozenset[str]: ...

    def densify_limits(self, phase: Phase) -> tuple[int, int]: ...

    def ends_stage(self, steps_done: int) -> bool: ...

    def attach(self, trainer: Trainer, state: dict | None) -> None: ...

    def begin(self, trainer: Trainer, phase: Phase) -> None: ...

    def before_update(self, trainer: Trainer) -> None: ...

    def after_update(self, trainer: Trainer, phase: Phase, window: TimeWindow) -> None: ...

    def end(self, trainer: Trainer, phase: Phase, step: int, record: dict) -> None: ...

    def state_dict(self) -> dict: ...

    def model_extras(self, trainer: Trainer) -> dict: ...


#: What the coarse stage does not train: the BED equilibria and the deformation field (the
#: static stage renders the canonical Gaussians, so these get no gradient anyway).
STATIC_FROZEN = frozenset({"mu_eq", "t_eq", "grid", "decoder"})


class StagedSchedule:
    """The ordinary run (docs/training.md): `coarse.iterations` steps of static 3DGS, then
    `fine.iterations` steps with the deformation field on. The resolution warm-up spans both
    stages; the time window follows each stage's curriculum."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.total_steps = cfg.coarse.iterations + cfg.fine.iterations
        self.layer_sizes: list[int] = []

    def phase(self, step: int) -> Phase:
        c = self.cfg.coarse.iterations
        if step < c:
            return Phase("coarse", step, c)
        return Phase("fine", step - c, self.cfg.fine.iterations)

    def stage_config(self, phase: Phase) -> StageConfig:
        return self.cfg.coarse if phase.stage == "coarse" else self.cfg.fine

    def views(self, trainer: Trainer, layer: int) -> Views:
        return trainer.train_views

    def resolution_warmup(self, step: int, phase: Phase) -> tuple[int, int] | None:
        """(step, steps) of data.resolution_schedule: it spans the whole run."""
        return step, self.total_steps

    def time_window(self, trainer: Trainer, phase: Phase) -> TimeWindow:
        config = self.stage_config(phase)
        window = window_at(config, phase.it, phase.length, self.cfg.train.canonical_time,
                           trainer.scene.time_range)
        return widen_to_frames(window, trainer.train_views.times, config.min_window_frames)

    def frozen_groups(self, phase: Phase) -> frozenset[str]:
        return STATIC_FROZEN if phase.stage == "coarse" else frozenset()

    def densify_limits(self, phase: Phase) -> tuple[int, int]:
        return 0, self.cfg.densify.max_gaussians

    def ends_stage(self, steps_done: int) -> bool:
        return steps_done in (self.cfg.coarse.iterations, self.total_steps)

    def attach(self, trainer: Trainer, state: dict | None) -> None:
        pass

    def begin(self, trainer: Trainer, phase: Phase) -> None:
        if phase.stage == "fine":
            start_deformation(trainer)

    def before_update(self, trainer: Trainer) -> None:
        pass

    def after_update(self, trainer: Trainer, phase: Phase, window: TimeWindow) -> None:
        """The time curriculum: while the window is narrower than the time range, the
        space-time hex-plane rows outside it stay at its edge rows (nehad.curriculum)."""
        if phase.deforms and self.cfg.train.hold_time_planes:
            lo, hi = trainer.scene.time_range
            if not (window.lo <= lo and window.hi >= hi):
                hold_time_planes(trainer.model.field.hexplane, window,
                                 self.cfg.train.hold_mode)

    def end(self, trainer: Trainer, phase: Phase, step: int, record: dict) -> None:
        pass

    def state_dict(self) -> dict:
        return {}

    def model_extras(self, trainer: Trainer) -> dict:
        return {}


def start_deformation(trainer: Trainer) -> None:
    """The coarse -> fine boundary (docs/training.md, "The recipe"): the BED equilibria (the
    paper, Sec. "Boltzmann Equilibrium Decomposition") start at the Gaussians, t_eq at
    train.canonical_time; the hex-plane box is fitted to the Gaussians and the trunk standardised
    when configured; the densification statistics start afresh."""
    cfg = trainer.cfg.train
    g = trainer.model.gaussians
    g.reset_equilibrium(cfg.canonical_time)
    if cfg.revive_opacity > 0:
        with torch.no_grad():
            floor = float(np.log(cfg.revive_opacity / (1.0 - cfg.revive_opacity)))
            g.opacity_logits.clamp_(min=floor)
    if cfg.fit_box_to_gaussians:
        box = gaussian_bounds(g, cfg.fit_box_padding)
        if box is not None:
            trainer.aabb = box
            trainer.model.field.set_aabb(torch.as_tensor(box))
    if cfg.standardize_trunk and len(g) > 1:
        trainer.model.field.standardize_trunk(g.means.detach(), cfg.canonical_time,
                                              g.log_scales.detach(), g.quats.detach())
    trainer.densify_state.reset(len(g))


def gaussian_bounds(gaussians: GaussianParameters, padding: float,
                    min_opacity: float = 0.1) -> np.ndarray | None:
    """(2, 3) box around the Gaussians with opacity >= `min_opacity` (0.5 and 99.5
    percentiles of their means, so a few stray ones do not stretch it), padded by `padding` of
    its size on each side; None if fewer than 10 Gaussians qualify."""
    with torch.no_grad():
        keep = torch.sigmoid(gaussians.opacity_logits).reshape(-1) >= min_opacity
        pts = gaussians.means[keep].numpy()
    if len(pts) < 10:
        return None
    lo, hi = np.percentile(pts, 0.5, axis=0), np.percentile(pts, 99.5, axis=0)
    size = np.maximum(hi - lo, 1e-3)
    pad = padding * size.max()
    return np.stack([lo - pad, hi + pad]).astype(np.float32)


__all__ = ["Phase", "STATIC_FROZEN", "Schedule", "StagedSchedule", "gaussian_bounds",
           "start_deformation"]
