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

    @classmethod
    def for_stage(cls, stage, length: int, interval: int) -> "DensifySchedule":
        """From a StageConfig's fractions (nehad.config) and the stage's length."""
        def at(frac: float) -> int:
            return int(math.floor(frac * length + 0.5))

        every = lambda frac: max(at(frac), 1) if frac > 0 else 0
        return cls(at(stage.densify_from), at(stage.densify_until), int(interval),
                   every(stage.opacity_reset_every), every(stage.prune_large_every))

    def densifies(self, it: int) -> bool:
        return self.start <= it < self.stop and it > 0 and it % self.interval == 0

    def resets(self, it: int) -> bool:
        return (self.reset_every > 0 and it > 0 and it < self.stop
                and it % self.reset_every == 0)

    def recovering(self, it: int) -> bool:
        """Whether iteration `it` lies in the first quarter of the period after an opacity reset
        (the opacities are still growing back: a render then misses what the model holds)."""
        if self.reset_every <= 0:
            return False
        last = (it // self.reset_every) * self.reset_every  # resets at 0 < last < stop
        return 0 < last < self.stop and it - last < max(self.reset_every // 4, 1)

    def prunes_large(self, it: int) -> bool:
        return (self.prune_large_every > 0 and self.reset_every > 0 and it > self.reset_every
                and it % self.prune_large_every == 0)


@dataclass
class DensifyState:
    grad_accum: torch.Tensor  # (N,) summed view-space gradient norms
    visible_count: torch.Tensor  # (N,) views in which each Gaussian was visible
    max_radii: torch.Tensor  # (N,) largest screen radius seen

    @classmethod
    def zeros(cls, n: int) -> "DensifyState":
        return cls(torch.zeros(n), torch.zeros(n), torch.zeros(n))

    def kept(self, mask: torch.Tensor, added: int = 0) -> "DensifyState":
        """The statistics of the Gaussians `mask` keeps, then `added` new ones at zero (the
        order `keep_gaussians` then `append_gaussians` leaves them in)."""
        def grow(v):
            return torch.cat([v[mask], torch.zeros(added)])

        return DensifyState(grow(self.grad_accum), grow(self.visible_count),
                            grow(self.max_radii))


class DensifyStrategy:
    """3DGS densification; `iteration` is counted from the start of the current stage."""

    def __init__(self, cfg: DensifyConfig, extent: float,
                 schedule: DensifySchedule | None = None):
        self.cfg = cfg
        self.extent = float(extent)
        self.schedule = schedule or DensifySchedule(0, 0, cfg.interval, 0, 0)
        self.state = DensifyState.zeros(0)
        #: The first `frozen` Gaussians are never cloned, split, pruned or opacity-reset: the
        #: frozen lower layers of layered training (docs/design.md section 8, nehad.lod). New ones go after them.
        self.frozen = 0

    def reset(self, n: int) -> None:
        self.state = DensifyState.zeros(n)

    def state_dict(self) -> dict:
        s = self.state
        return {"grad_accum": s.grad_accum, "visible_count": s.visible_count,
                "max_radii": s.max_radii}

    def load_state_dict(self, d: dict) -> None:
        self.state = DensifyState(d["grad_accum"], d["visible_count"], d["max_radii"])

    @torch.no_grad()
    def record_view(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int,
                    height: int) -> None:
        """Accumulate one rendered view's statistics (call after backward)."""
        s = self.state
        if s.grad_accum.shape[0] != radii.shape[0]:
            self.reset(radii.shape[0])
            s = self.state
        visible = radii > 0
        if means2d_grad is None or not visible.any():
            return
        s.grad_accum[visible] += viewspace_grad_norm(means2d_grad[visible], width, height)
        s.visible_count[visible] += 1
        s.max_radii[visible] = torch.maximum(s.max_radii[visible], radii[visible].float())

    @torch.no_grad()
    def step_post_backward(self, params: GaussianParameters, optimizer, iteration: int,
                           generator: torch.Generator | None = None) -> dict:
        """Densify / prune / reset as `self.schedule` says; returns what it did."""
        did = {}
        if self.schedule.densifies(iteration):
            did.update(self._densify_and_prune(params, optimizer, iteration, generator))
        if self.schedule.resets(iteration):
            self._reset_opacity(params, optimizer)
            did["opacity_reset"] = True
        return did

    def _densify_and_prune(self, params, optimizer, iteration, generator) -> dict:
        cfg = self.cfg
        s = self.state
        n = len(params)
        if s.grad_accum.shape[0] != n:
            self.reset(n)
            return {}
        grads = s.grad_accum / s.visible_count.clamp_min(1)
        grads[:self.frozen] = -1.0  # frozen layers never densify (below any threshold)
        max_scale = torch.exp(params.log_scales).max(dim=1).values
        hot = grads >= cfg.grad_threshold
        if cfg.max_gaussians > 0:
            # the cap counts the trainable Gaussians: in a layered run, those of this layer
            room = max(cfg.max_gaussians - (n - self.frozen), 0)
            if int(hot.sum()) > room:
                # keep the hottest ones within the cap (a split adds one net Gaussian, a clone one)
                order = torch.argsort(grads, descending=True)
                hot = torch.zeros_like(hot)
                hot[order[:room]] = True
                hot &= grads >= cfg.grad_threshold
        small = max_scale <= cfg.percent_dense * self.extent
        clone = hot & small
        split = hot & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())

        new = {name: getattr(params, name)[clone].detach().clone() for name in params.NAMES}
        if n_split:
            new_split = self._split_children(params, split, generator)
            new = {k: torch.cat([new[k], new_split[k]], 0) for k in new}
        if new["means"].shape[0]:
            append_gaussians(params, optimizer, new)
        # prune: split parents, transparent ones, and (after prune_interval) oversized ones
        total = len(params)
        prune = torch.zeros(total, dtype=torch.bool)
        prune[:n][split] = True
        prune |= torch.sigmoid(params.opacity_logits).detach() < cfg.min_opacity
        if self.schedule.prunes_large(iteration):
            radii = torch.cat([s.max_radii, torch.zeros(total - n)])
            big_screen = radii > cfg.max_screen_size
            big_world = torch.exp(params.log_scales).detach().max(dim=1).values > 0.1 * self.extent
            prune |= big_screen | big_world
        prune[:self.frozen] = False
        n_prune = int(prune.sum())
        if n_prune:
            keep_gaussians(params, optimizer, ~prune)
        self.reset(len(params))
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune, "gaussians": len(params)}

    @staticmethod
    def _split_children(params, mask, generator, n_children: int = 2) -> dict:
        """Two children per parent, positions sampled from the parent's Gaussian, scales / 1.6."""
        scales = torch.exp(params.log_scales[mask]).detach()
        rot = quat_to_rotmat(params.quats[mask].detach())
        scales_rep = scales.repeat(n_children, 1)
        noise = torch.randn(scales_rep.shape, generator=generator) * scales_rep
        offsets = (rot.repeat(n_children, 1, 1) @ noise[..., None])[..., 0]
        out = {}
        for name in params.NAMES:
            out[name] = getattr(params, name)[mask].detach().repeat(
                n_children, *([1] * (getattr(params, name).dim() - 1)))
        out["means"] = out["means"] + offsets
        out["log_scales"] = torch.log(scales_rep / (0.8 * n_children))
        return out

    def _reset_opacity(self, params, optimizer) -> None:
        capped = torch.minimum(params.opacity_logits.detach(),
                               torch.logit(torch.tensor(0.01)))
        capped[:self.frozen] = params.opacity_logits.detach()[:self.frozen]
        _replace_parameter(params, optimizer, "opacity_logits", capped,
                           lambda v: torch.zeros_like(v))
