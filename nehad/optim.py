"""The optimizer of a run (docs/training.md): Adam with one parameter group per Gaussian
attribute and per part of the deformation field, 3DGS's learning rates, and the exponential
decays over each stage (layer)."""

from __future__ import annotations

import math

import torch

from nehad.config import OptimConfig


def exp_lr(step: int, total: int, lr_init: float, lr_final: float) -> float:
    """Log-linear interpolation from lr_init to lr_final over `total` steps (3DGS schedule)."""
    if total <= 0 or lr_init <= 0:
        return lr_init
    t = min(max(step / total, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(max(lr_final, 1e-30)) * t)


def make_optimizer(model, o: OptimConfig, extent: float) -> torch.optim.Optimizer:
    """Adam over `model` (a NeHaDModel); positions and velocities learn in units of the scene
    extent. The equilibria and the field start frozen (the static stage)."""
    g = model.gaussians
    rates = {"means": o.position_lr_init * extent, "sh_dc": o.sh_dc_lr,
             "sh_rest": o.sh_dc_lr / o.sh_rest_lr_divisor, "opacity_logits": o.opacity_lr,
             "log_scales": o.scaling_lr, "quats": o.rotation_lr, "mu_eq": 0.0, "t_eq": 0.0,
             "life_rate": o.life_rate_lr, "velocity": o.velocity_lr * extent}
    groups = [{"name": name, "params": [getattr(g, name)], "lr": lr}
              for name, lr in rates.items()]
    field_groups = model.field.param_groups()
    groups.append({"name": "grid", "params": list(field_groups["grid"]), "lr": 0.0})
    groups.append({"name": "decoder", "params": list(field_groups["decoder"]), "lr": 0.0})
    # fused: one pass per parameter instead of a chain of element-wise ops (docs/performance.md)
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)


def set_learning_rates(optimizer, o: OptimConfig, extent: float, phase,
                       frozen: frozenset[str]) -> None:
    """The rates of iteration `phase.it` of a stage (layer) of `phase.length`: exponential
    decays for the positions, the hex-plane and the decoder; `frozen` groups get 0."""
    it, length = phase.it, phase.length
    decoder_final = o.decoder_lr if o.decoder_lr_final is None else o.decoder_lr_final
    decays = {"grid": (o.grid_lr_init, o.grid_lr_final), "decoder": (o.decoder_lr, decoder_final)}
    for group in optimizer.param_groups:
        name = group["name"]
        if name in ("means", "mu_eq"):
            lr = exp_lr(it, length, o.position_lr_init, o.position_lr_final) * extent
        elif name == "t_eq":
            lr = o.t_eq_lr
        elif name in decays:
            lr = exp_lr(it, length, *decays[name])
        else:
            continue  # constant learning rates
        group["lr"] = 0.0 if name in frozen else lr


__all__ = ["exp_lr", "make_optimizer", "set_learning_rates"]
