"""Adaptive density control of 3DGS as a strategy object (gsplat's layout): the training loop
calls `step_post_backward` and never decides itself when to clone, split, prune or reset.

Rules (3DGS, docs/design.md section 5): inside the stage's densification window, every `interval`
iterations, Gaussians whose mean view-space (NDC) gradient exceeds `grad_threshold` are cloned
when small (max scale <= percent_dense * extent) and split in two when large; Gaussians with
opacity < `min_opacity` are pruned, and too large ones too once the first opacity reset has passed
(every `prune_large_every`). Opacities are reset to at most 0.01 every `reset_every`, only inside
the densification window, so a reset is always followed by densification steps that recover from
it and never falls on a stage's last step (docs/training.md). Every per-Gaussian parameter takes
part, so densified children inherit mu_eq and t_eq (docs/design.md section 4.7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from nehad.config import DensifyConfig
from nehad.gaussians import GaussianParameters
from nehad.splat.projection import quat_to_rotmat
from nehad.splat.rasterize import viewspace_grad_norm


def _replace_parameter(module: nn.Module, optimizer: torch.optim.Optimizer, name: str,
                       new_value: torch.Tensor, state_fn) -> None:
    """Swap parameter `name` for `new_value`, carrying its Adam state through `state_fn`."""
    old = getattr(module, name)
    new = nn.Parameter(new_value.detach().clone().requires_grad_(True))
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state:
                    optimizer.state[new] = {
                        k: (state_fn(v) if torch.is_tensor(v) and v.dim() > 0 else v)
                        for k, v in state.items()}
    setattr(module, name, new)


def keep_gaussians(params: GaussianParameters, optimizer, mask: torch.Tensor) -> None:
    """Keep only the Gaussians where `mask` is True (parameters and optimizer state)."""
    for name in params.NAMES:
        _replace_parameter(params, optimizer, name, getattr(params, name)[mask],
                           lambda v: v[mask])


def append_gaussians(params: GaussianParameters, optimizer, new: dict) -> None:
    """Append Gaussians (a tensor per parameter name); their optimizer state starts at zero."""
    for name in params.NAMES:
        extra = new[name]
        _replace_parameter(params, optimizer, name,
                           torch.cat([getattr(params, name).detach(), extra], 0),
                           lambda v, e=extra: torch.cat([v, torch.zeros_like(e)], 0))


@dataclass(frozen=True)
class DensifySchedule:
    """When densification runs within one stage, in iterations counted from the stage's start
    (1-based: `step_post_backward` is called after iteration `it` with it = 1 .. length)."""

    start: int  # first iteration that densifies
    stop: int  # no densification or opacity reset from this iteration on
    interval: int
    reset_every: int  # 0 = never
    prune_large_every: int  # 0 = never
    prune_transparent: bool = True
    length: int = 0  # the stage's iterations

    @classmethod
    def for_stage(cls, stage, length: int, interval: int) -> "DensifySchedule":
        """From a StageConfig's fractions (nehad.config) and the stage's length."""
        def at(frac: float) -> int:
            return int(math.floor(frac * length + 0.5))

        every = lambda frac: max(at(frac), 1) if frac > 0 else 0
        return cls(at(stage.densify_from), at(stage.densify_until), int(interval),
                   every(stage.opacity_reset_every), every(stage.prune_large_every),
                   bool(getattr(stage, "prune_transparent", True)), int(length))

    def densifies(self, it: int) -> bool:
        return self.start <= it < self.stop and it > 0 and it % self.interval == 0

    def resets(self, it: int) -> bool:
        return (self.reset_every > 0 and it > 0 and it < self.stop
                and it % self.reset_every == 0)

    def recovering(self, it: int, part: float = 0.25) -> bool:
        """Whether iteration `it` lies in the first `part` of the period after an opacity reset
        (the opacities are still growing back: a render then misses what the model holds)."""
        if self.reset_every <= 0:
            return False
        last = (it // self.reset_every) * self.reset_every  # resets at 0 < last < stop
        return 0 < last < self.stop and it - last < max(int(self.reset_every * part), 1)

    def prunes_large(self, it: int) -> bool:
        return (self.prune_large_every > 0 and self.reset_every > 0 and it > self.reset_every
                and it % self.prune_large_every == 0)


def spawn_children(params: GaussianParameters, rows, n_children: int,
                   generator: torch.Generator | None) -> dict:
    """`n_children` copies of each Gaussian in `rows` (a mask or a slice), every parameter
    inherited (so children keep mu_eq and t_eq, docs/design.md section 4.7), their positions drawn
    from the parent's Gaussian: mu + R (s * z), z ~ N(0, I). The caller sets their scales (a 3DGS
    split, `nehad.lod`'s layer seeding)."""
    scales = torch.exp(params.log_scales[rows]).detach().repeat(n_children, 1)
    rot = quat_to_rotmat(params.quats[rows].detach()).repeat(n_children, 1, 1)
    noise = torch.randn(scales.shape, generator=generator) * scales
    out = {}
    for name in params.NAMES:
        value = getattr(params, name)[rows].detach()
        out[name] = value.repeat(n_children, *([1] * (value.dim() - 1))).clone()
    out["means"] = out["means"] + (rot @ noise[..., None])[..., 0]
    return out


@dataclass
class DensifyState:
    """Per-Gaussian statistics the strategy accumulates between densification steps; the trainer
    owns it (checkpointed) and passes it to every hook."""

    grad_accum: torch.Tensor  # (N,) summed view-space gradient norms
    visible_count: torch.Tensor  # (N,) views in which each Gaussian was visible
    max_radii: torch.Tensor  # (N,) largest screen radius seen

    @classmethod
    def zeros(cls, n: int) -> "DensifyState":
        return cls(torch.zeros(n), torch.zeros(n), torch.zeros(n))

    def reset(self, n: int) -> None:
        """Start afresh for `n` Gaussians."""
        self.grad_accum, self.visible_count, self.max_radii = (torch.zeros(n) for _ in range(3))

    def keep(self, mask: torch.Tensor, added: int = 0) -> None:
        """Keep the statistics of the Gaussians `mask` keeps, then `added` new ones at zero (the
        order `keep_gaussians` then `append_gaussians` leaves them in)."""
        def grow(v):
            return torch.cat([v[mask], torch.zeros(added)])

        self.grad_accum, self.visible_count, self.max_radii = (
            grow(self.grad_accum), grow(self.visible_count), grow(self.max_radii))

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "visible_count": self.visible_count,
                "max_radii": self.max_radii}

    @classmethod
    def from_state_dict(cls, d: dict) -> "DensifyState":
        return cls(d["grad_accum"], d["visible_count"], d["max_radii"])


@dataclass(frozen=True)
class ViewStats:
    """What one rendered view of a step tells the strategy (after backward)."""

    means2d_grad: torch.Tensor | None  # (N, 2) gradient of the projected means
    radii: torch.Tensor  # (N,) screen radii (0: not visible)
    width: int
    height: int


@dataclass(frozen=True)
class DensifyStrategy:
    """3DGS adaptive density control (see the module doc), in gsplat's manner: this object owns
    when it acts within a stage (`timing`) and what it does (`step_post_backward`); the state is
    the trainer's and comes in as an argument, as do the frozen Gaussians of layered training
    (`frozen`: the first `frozen` are never cloned, split, pruned or opacity-reset; new ones go
    after them) and the cap of the current layer."""

    cfg: DensifyConfig
    extent: float

    def timing(self, stage, length: int) -> DensifySchedule:
        """When densification runs in a stage (a StageConfig) of `length` iterations."""
        return DensifySchedule.for_stage(stage, length, self.cfg.interval)

    @torch.no_grad()
    def step_post_backward(self, params: GaussianParameters, optimizer,
                           state: DensifyState, iteration: int, timing: DensifySchedule,
                           views: list[ViewStats], *, frozen: int = 0,
                           max_gaussians: int | None = None,
                           generator: torch.Generator | None = None) -> dict:
        """After iteration `iteration` (1-based, within the stage): record the step's views,
        then densify / prune / reset as `timing` says; returns what it did."""
        for view in views:
            self._record_view(state, view)
        cap = self.cfg.max_gaussians if max_gaussians is None else int(max_gaussians)
        did = {}
        if timing.densifies(iteration):
            did.update(self._densify_and_prune(params, optimizer, state, iteration, timing,
                                               frozen, cap, generator))
        if timing.resets(iteration):
            self._reset_opacity(params, optimizer, frozen)
            did["opacity_reset"] = True
        return did

    @staticmethod
    def _record_view(state: DensifyState, view: ViewStats) -> None:
        if state.grad_accum.shape[0] != view.radii.shape[0]:
            state.reset(view.radii.shape[0])
        visible = view.radii > 0
        if view.means2d_grad is None or not visible.any():
            return
        state.grad_accum[visible] += viewspace_grad_norm(view.means2d_grad[visible], view.width,
                                                         view.height)
        state.visible_count[visible] += 1
        state.max_radii[visible] = torch.maximum(state.max_radii[visible],
                                                 view.radii[visible].float())

    def _hot(self, state: DensifyState, n: int, frozen: int, cap: int) -> torch.Tensor:
        """Gaussians whose mean view-space gradient reaches the threshold, the hottest ones
        within the cap (which counts the trainable Gaussians: in a layered run, this layer's)."""
        grads = state.grad_accum / state.visible_count.clamp_min(1)
        grads[:frozen] = -1.0  # frozen layers never densify (below any threshold)
        hot = grads >= self.cfg.grad_threshold
        if cap > 0:
            room = max(cap - (n - frozen), 0)
            if int(hot.sum()) > room:
                # a split adds one net Gaussian, a clone one
                order = torch.argsort(grads, descending=True)
                hot = torch.zeros_like(hot)
                hot[order[:room]] = True
                hot &= grads >= self.cfg.grad_threshold
        return hot

    def _densify_and_prune(self, params, optimizer, state, iteration, timing, frozen, cap,
                           generator) -> dict:
        n = len(params)
        if state.grad_accum.shape[0] != n:
            state.reset(n)
            return {}
        hot = self._hot(state, n, frozen, cap)
        max_scale = torch.exp(params.log_scales).max(dim=1).values
        small = max_scale <= self.cfg.percent_dense * self.extent
        clone, split = hot & small, hot & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())
        new = {name: getattr(params, name)[clone].detach().clone() for name in params.NAMES}
        if n_split:
            children = spawn_children(params, split, 2, generator)
            children["log_scales"] = torch.log(
                torch.exp(params.log_scales[split]).detach().repeat(2, 1) / (0.8 * 2))
            new = {k: torch.cat([new[k], children[k]], 0) for k in new}
        if new["means"].shape[0]:
            append_gaussians(params, optimizer, new)
        prune = self._to_prune(params, state, n, split, iteration, timing, frozen)
        n_prune = int(prune.sum())
        if n_prune:
            keep_gaussians(params, optimizer, ~prune)
        state.reset(len(params))
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune, "gaussians": len(params)}

    def _to_prune(self, params, state, n, split, iteration, timing, frozen) -> torch.Tensor:
        """Split parents, transparent Gaussians, and (after the first opacity reset, every
        prune_large_every) oversized ones; never the frozen ones."""
        cfg = self.cfg
        total = len(params)
        prune = torch.zeros(total, dtype=torch.bool)
        prune[:n][split] = True
        if timing.prune_transparent:
            prune |= torch.sigmoid(params.opacity_logits).detach() < cfg.min_opacity
        if timing.prunes_large(iteration):
            radii = torch.cat([state.max_radii, torch.zeros(total - n)])
            big_screen = radii > cfg.max_screen_size
            big_world = torch.exp(params.log_scales).detach().max(dim=1).values > 0.1 * self.extent
            prune |= big_screen | big_world
        prune[:frozen] = False
        return prune

    @staticmethod
    def _reset_opacity(params, optimizer, frozen: int) -> None:
        """Opacities to at most 0.01, except the frozen ones and those of Gaussians with a
        finite life (nehad.carve): a reset clears floaters that are drawn at every time, while
        a Gaussian that lives around one time is seen by a few views only and would be pruned
        before they could bring it back."""
        capped = torch.minimum(params.opacity_logits.detach(),
                               torch.logit(torch.tensor(0.01)))
        capped[:frozen] = params.opacity_logits.detach()[:frozen]
        short = params.mortal()
        capped[short] = params.opacity_logits.detach()[short]
        _replace_parameter(params, optimizer, "opacity_logits", capped,
                           lambda v: torch.zeros_like(v))
