"""The optimizer of a run (docs/training.md): Adam with one parameter group per Gaussian
attribute and per part of the deformation field, 3DGS's learning rates, and the exponential
decays over each stage (layer)."""

from __future__ import annotations

import math

import torch
from torch.optim.adam import adam as adam_update

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
    return TrainingAdam(groups, lr=0.0, eps=1e-15, fused=True)


class TrainingAdam(torch.optim.Adam):
    """torch's fused Adam, except that a group named "grid" whose parameters are dense views of
    one buffer, one after the other (the hex-plane's planes, `nehad.field.hexplane.HexPlane`:
    channel-last (1, C, H, W) views of one flat array), is updated as ONE flat array. Its
    moments are kept as views of two flat arrays of the same layout; its gradients are read as
    one flat array where they are views of one buffer in that layout (as `zero_grad` installs
    them) and copied into a third one otherwise; torch's fused Adam (`torch.optim.adam.adam`)
    then runs once on the flat arrays.
    Per plane, it took 2.6-4.2 ms a step for the `cpu` preset's 2.43 M plane values, which it
    reads through their channel-last strides; flat, 0.8-1.4 ms (docs/performance.md, "The
    planes' Adam step as one array"). The arithmetic is the kernel's own, element by element,
    so the result is the per-plane step's (tests/test_optim.py). Anything else (planes without
    one buffer, some without a gradient, steps that differ between them, amsgrad, maximize, a
    grad scaler) takes torch's per-parameter path. The state is per plane as before, so
    checkpoints are read and written as torch's Adam does."""

    def zero_grad(self, set_to_none: bool = True) -> None:
        """torch's, except that the planes of a "grid" group that shares one buffer get zeroed
        views of one flat gradient array of their layout as their `.grad`: autograd then adds
        every gradient of theirs (the lookup's, the regularisers') into it in place, where with
        no `.grad` it copied the first one into a fresh tensor, and `step` reads the array as it
        is. A group whose array no gradient reached by `step` is handed to torch's step
        without gradients (None), as after torch's zero_grad."""
        super().zero_grad(set_to_none)
        self._untouched = {}
        for group in self.param_groups:
            params = group["params"]
            if group.get("name") != "grid" or not params or _flat_alias(params) is None:
                continue
            grad = self._arrays(params)["grad"]
            grad.zero_()
            for p, view in zip(params, _views(grad, params)):
                p.grad = view
            # the views share the array's version counter: unchanged at `step`, none was written
            self._untouched[id(group)] = (grad, grad._version)

    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:  # zeroed by zero_grad and never written: no gradient
            grad, version = getattr(self, "_untouched", {}).get(id(group), (None, None))
            held = group["params"][0].grad if grad is not None else None
            if (held is not None and held.data_ptr() == grad.data_ptr()
                    and grad._version == version):
                for p in group["params"]:
                    p.grad = None
        self._untouched = {}
        flat = [group for group in self.param_groups
                if group.get("name") == "grid" and self._flat_step(group)]
        held = [(p, p.grad) for group in flat for p in group["params"]]
        for p, _ in held:  # the flat groups are done: torch's step passes over them
            p.grad = None
        try:
            super().step()
        finally:
            for p, grad in held:
                p.grad = grad
        return loss

    @torch.no_grad()
    def _flat_step(self, group) -> bool:
        """Update `group` as one flat array (class docstring); False, with nothing changed,
        where it cannot."""
        params = group["params"]
        if (not params or group["amsgrad"] or group["maximize"] or group["weight_decay"] != 0
                or getattr(self, "grad_scale", None) is not None
                or any(p.grad is None for p in params)):
            return False
        buffer = _flat_alias(params)
        if buffer is None or any(p.grad.shape != p.shape for p in params):
            return False
        states = [self.state[p] for p in params]
        steps = [s.get("step") for s in states]
        fresh = all(s is None for s in steps)
        if not fresh and (any(s is None for s in steps)
                          or any(float(s) != float(steps[0]) for s in steps)):
            return False
        moments = self._flat_moments(params, states)
        grad = _flat_alias([p.grad for p in params])
        if grad is None or any(p.grad.stride() != p.stride() for p in params):
            grad = moments["grad"]  # separate tensors (or another layout): copied, by index
            for p, view in zip(params, _views(grad, params)):
                view.copy_(p.grad)
        if fresh:  # a first step: torch's fused Adam starts its count at 0
            for s in states:
                s["step"] = torch.zeros((), dtype=torch.float32)
        counts = [s["step"] for s in states]
        torch._foreach_add_(counts[1:], 1)  # the first is counted by the call below
        beta1, beta2 = group["betas"]
        adam_update([buffer], [grad], [moments["exp_avg"]], [moments["exp_avg_sq"]], [],
                    counts[:1], fused=True, amsgrad=False, beta1=beta1, beta2=beta2,
                    lr=group["lr"], weight_decay=0.0, eps=group["eps"], maximize=False)
        return True

    def _arrays(self, params) -> dict:
        """{"exp_avg", "exp_avg_sq", "grad"}: flat arrays of the group's size, kept between
        steps (made anew, zeros, for another group of planes)."""
        cache = getattr(self, "_flat_cache", None)
        if cache is None:
            cache = self._flat_cache = {}
        key = tuple(id(p) for p in params)
        arrays = cache.get(key)
        if arrays is None:
            total = sum(p.numel() for p in params)
            arrays = {name: torch.zeros(total, dtype=params[0].dtype)
                      for name in ("exp_avg", "exp_avg_sq", "grad")}
            cache.clear()
            cache[key] = arrays
        return arrays

    def _flat_moments(self, params, states) -> dict:
        """`_arrays(params)`, each plane's moments in `states` made views of the first two
        (their values copied in where they were separate tensors: a fresh state is zeros, a
        loaded one its values)."""
        arrays = self._arrays(params)
        for name in ("exp_avg", "exp_avg_sq"):
            for p, state, view in zip(params, states, _views(arrays[name], params)):
                held = state.get(name)
                if held is not None and _same_memory(held, view):
                    continue
                if held is None:
                    view.zero_()
                else:
                    view.copy_(held)
                state[name] = view
        return arrays


def _flat_alias(params):
    """A flat (numel,) view of the buffer that `params` are dense views of (each filling its
    numel places in any axis order), one after the other in their order; None otherwise."""
    first = params[0]
    if first.device.type != "cpu" or not first.dtype.is_floating_point:
        return None
    storage = first.untyped_storage().data_ptr()
    offset = first.storage_offset()
    for p in params:
        if (p.dtype != first.dtype or p.untyped_storage().data_ptr() != storage
                or p.storage_offset() != offset or not _dense(p)):
            return None
        offset += p.numel()
    return torch.as_strided(first.detach(), (offset - first.storage_offset(),), (1,),
                            first.storage_offset())


def _dense(t: torch.Tensor) -> bool:
    """Whether t's elements fill numel consecutive places of its storage (any axis order)."""
    size = 1
    for stride, n in sorted((s, n) for s, n in zip(t.stride(), t.shape) if n != 1):
        if stride != size:
            return False
        size *= n
    return True


def _views(flat: torch.Tensor, params) -> list:
    """Views of `flat` with each parameter's shape and strides, one after the other."""
    out, lo = [], flat.storage_offset()
    for p in params:
        out.append(flat.as_strided(p.shape, p.stride(), lo))
        lo += p.numel()
    return out


def _same_memory(a: torch.Tensor, b: torch.Tensor) -> bool:
    return (a.data_ptr() == b.data_ptr() and a.stride() == b.stride() and a.shape == b.shape
            and a.dtype == b.dtype)


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


__all__ = ["TrainingAdam", "exp_lr", "make_optimizer", "set_learning_rates"]
