"""The module that is traced into the `nehad-onnx/1` graph (docs/design.md section 7).

`ExportGraph(model, sh_degree)(time)` computes what `NeHaDModel.gaussians_at(t)` computes
(activated means, scales, unit wxyz quats, opacities, SH truncated to `sh_degree`), but takes the
time as a float32 tensor of shape [1] instead of a Python float, so that the time stays a graph
input instead of being baked in as a constant. The canonical Gaussians (with mu_eq, t_eq) and the
field's weights are the model's parameters and buffers: they become initializers.

The deformation is written as :class:`nehad.export.deform_graph.FastDeform`: the same function,
rearranged for onnxruntime (time-independent parts as constant subgraphs, linear maps
precomposed), with the HNN gradient in closed form (docs/design.md section 4.4), never with autograd. The export
checks it against the torch model's own `gaussians_at` (docs/design.md section 7 parity).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from nehad.export.deform_graph import FastDeform

OUTPUT_NAMES = ("means", "scales", "quats", "opacities", "sh")
LAYER_OUTPUT = "layer"  # docs/design.md section 7: with LOD layers, each Gaussian's layer [N] int32


def closed_form_copy(model) -> nn.Module:
    """A deep copy of `model` in eval mode whose HNN gradient is the closed form (no autograd);
    the caller's model is left untouched."""
    model = copy.deepcopy(model).eval()
    model.field.set_grad_mode("closed_form")
    if getattr(model.field.cfg, "mipmap", False):  # docs/design.md section 8: pyramids as initializers
        model.field.hexplane.freeze_pyramids_for_export()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


class ExportGraph(nn.Module):
    """forward(time [1]) -> (means [N,3], scales [N,3], quats [N,4], opacities [N], sh [N,K,3])
    and, when `layer` ([N] layer index of each Gaussian, docs/design.md section 8) is given, `layer` [N] int32."""

    def __init__(self, model, sh_degree: int, layer=None, static=None):
        super().__init__()
        if not 0 <= int(sh_degree) <= model.gaussians.sh_degree:
            raise ValueError(f"ExportGraph: sh_degree {sh_degree} outside 0..{model.gaussians.sh_degree}")
        self.sh_degree = int(sh_degree)
        self.k = (self.sh_degree + 1) ** 2
        self.split = static is not None and static.num_static > 0
        if self.split:  # nehad.export.static_split: the field runs on the moving Gaussians only
            model = self._moving_part(model, static)
        self.model = model
        self.deform = FastDeform(model, sh_degree)
        self.with_layer = layer is not None
        if self.with_layer:
            self.register_buffer("layer", torch.as_tensor(layer, dtype=torch.int32).reshape(-1))

    def _moving_part(self, model, static):
        """A copy of `model` holding only the Gaussians that move; the frozen outputs of the
        others and the permutation back to the model's order become buffers."""
        from nehad.gaussians import GaussianParameters

        g = model.gaussians
        mask = torch.as_tensor(static.mask)
        moving, still = torch.nonzero(~mask).reshape(-1), torch.nonzero(mask).reshape(-1)
        order = torch.cat([moving, still])
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(len(order))
        self.register_buffer("inverse", inverse)
        for name, value in zip(OUTPUT_NAMES[:4], static.frozen[:4]):
            self.register_buffer(f"frozen_{name}", torch.as_tensor(value, dtype=torch.float32))
        # SH the field does not deform pass through whole (no gather); deformed SH are split too
        self.sh_passes = not model.field.cfg.deform_opacity_sh
        if self.sh_passes:
            self.register_buffer("sh_all", torch.cat([g.sh_dc, g.sh_rest], 1)[:, :self.k]
                                 .detach().clone())
        else:
            self.register_buffer("frozen_sh", torch.as_tensor(static.frozen[4],
                                                              dtype=torch.float32))
        part = copy.copy(model)
        part._modules = dict(model._modules)
        part._modules["gaussians"] = GaussianParameters(
            *(getattr(g, name).detach()[moving] for name in GaussianParameters.NAMES))
        part._modules["gaussians"].drift_window = g.drift_window
        return part

    @property
    def output_names(self) -> tuple[str, ...]:
        return OUTPUT_NAMES + ((LAYER_OUTPUT,) if self.with_layer else ())

    def forward(self, time: torch.Tensor):
        # NeHaDModel.gaussians_at, with the time kept a tensor (a graph input)
        g = self.model.gaussians
        out = self.deform(g.means, g.log_scales, g.quats, g.opacity_logits,
                          torch.cat([g.sh_dc, g.sh_rest], 1), g.mu_eq, g.t_eq, time,
                          g.life_rate if g.has_life() else None,
                          g.drift_velocity() if g.drifts() else None)
        if self.split:  # moving rows, then the frozen ones, put back in the model's order
            merged = [torch.cat([o, getattr(self, f"frozen_{name}")], 0)[self.inverse]
                      for name, o in zip(OUTPUT_NAMES[:4], out[:4])]
            sh = (self.sh_all if self.sh_passes
                  else torch.cat([out[4], self.frozen_sh], 0)[self.inverse])
            out = tuple(merged) + (sh,)
        return out + (self.layer,) if self.with_layer else out


def reference_outputs(model, t: float, sh_degree: int, layer=None) -> list:
    """The torch model's own outputs at time t (`gaussians_at`, SH truncated to `sh_degree`, the
    layer column when given) as NumPy arrays: what the exported graph must match (docs/design.md section 7)."""
    k = (int(sh_degree) + 1) ** 2
    with torch.no_grad():
        out = [o.detach().cpu().numpy()
               for o in model.gaussians_at(torch.tensor([t], dtype=torch.float32))]
    out[4] = out[4][:, :k]
    if layer is not None:
        out.append(np.asarray(layer, np.int32).reshape(-1))
    return out


__all__ = ["ExportGraph", "LAYER_OUTPUT", "OUTPUT_NAMES", "closed_form_copy", "reference_outputs"]
