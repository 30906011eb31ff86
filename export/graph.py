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
from nehad.runtime.onnx_model import part_output_name  # docs/design.md section 7: "means.part0"

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


MIN_PART_ROWS = 2048  # moving Gaussians per part at least (`part_bounds`)


def part_bounds(moving: np.ndarray, parts: int, min_rows: int = MIN_PART_ROWS) -> list[int]:
    """Row boundaries 0 = b_0 < ... < b_P = N cutting N Gaussians (`moving` [N] bool: those the
    field deforms) into P <= `parts` contiguous ranges with about equal numbers of moving ones, at
    least `min_rows` each (P = 1 when there are fewer than 2 `min_rows`)."""
    moving = np.asarray(moving, bool).reshape(-1)
    n, m = len(moving), int(moving.sum())
    parts = max(1, min(int(parts), m // max(1, int(min_rows))))
    if parts == 1:
        return [0, n]
    # the row after which the cumulative moving count first reaches p m / P
    cum = np.cumsum(moving)
    cuts = [int(np.searchsorted(cum, p * m / parts, side="left")) + 1 for p in range(1, parts)]
    return [0] + cuts + [n]


class ExportGraph(nn.Module):
    """forward(time [1]) -> (means [N,3], scales [N,3], quats [N,4], opacities [N], sh [N,K,3])
    and, when `layer` ([N] layer index of each Gaussian, docs/design.md section 8) is given, `layer` [N] int32.

    With `parts` > 1 the rows are cut into contiguous parts (`part_bounds`), each deformed by its
    own copy of the graph's nodes (one set of weights), and the outputs are the parts'
    concatenation, followed by every part's own outputs (`part_output_name`): the runtime cuts
    the graph down to a share of the parts' outputs (onnxruntime runs every node of a graph
    whatever a run asks for) and runs the shares side by side on several cores (docs/design.md
    section 7; runtime/onnx_model.py)."""

    def __init__(self, model, sh_degree: int, layer=None, static=None, parts: int = 1,
                 min_part_rows: int = MIN_PART_ROWS):
        super().__init__()
        if not 0 <= int(sh_degree) <= model.gaussians.sh_degree:
            raise ValueError(f"ExportGraph: sh_degree {sh_degree} outside 0..{model.gaussians.sh_degree}")
        self.sh_degree = int(sh_degree)
        self.k = (self.sh_degree + 1) ** 2
        g = model.gaussians
        n = len(g)
        still = np.zeros(n, bool)
        if static is not None and static.num_static > 0:  # nehad.export.static_split
            still = np.asarray(static.mask, bool).reshape(-1)
        self.bounds = part_bounds(~still, parts, min_part_rows)
        self.model = model
        self.deform = FastDeform(model, sh_degree)
        # SH the field does not deform pass through whole (no gather)
        self.sh_passes = not model.field.cfg.deform_opacity_sh
        self.register_buffer("sh_all", torch.cat([g.sh_dc, g.sh_rest], 1)[:, :self.k]
                             .detach().clone())
        frozen_row = np.cumsum(still) - 1  # a static Gaussian's row in static.frozen
        self._parts = []
        for p, (a, b) in enumerate(zip(self.bounds[:-1], self.bounds[1:])):
            rows = np.arange(a, b)
            moving, kept = rows[~still[a:b]], rows[still[a:b]]
            self.register_buffer(f"moving_{p}", torch.as_tensor(moving, dtype=torch.int64))
            split = len(kept) > 0
            if split:  # moving rows, then the frozen ones, put back in the model's order
                order = np.concatenate([moving, kept]) - a
                inverse = np.empty_like(order)
                inverse[order] = np.arange(len(order))
                self.register_buffer(f"inverse_{p}", torch.as_tensor(inverse, dtype=torch.int64))
                for name, value in zip(OUTPUT_NAMES, static.frozen):
                    self.register_buffer(f"frozen_{name}_{p}", torch.as_tensor(
                        np.asarray(value)[frozen_row[kept]], dtype=torch.float32))
            self._parts.append((a, b, len(moving), split))
        self.with_layer = layer is not None
        if self.with_layer:
            self.register_buffer("layer", torch.as_tensor(layer, dtype=torch.int32).reshape(-1))

    @property
    def parts(self) -> int:
        return len(self._parts)

    @property
    def output_names(self) -> tuple[str, ...]:
        names = OUTPUT_NAMES + ((LAYER_OUTPUT,) if self.with_layer else ())
        if self.parts == 1:
            return names
        return names + tuple(part_output_name(name, p) for p in range(self.parts)
                             for name in self.part_names)

    @property
    def part_names(self) -> tuple[str, ...]:
        """The outputs that have part outputs: those that change with time (SH the field does
        not deform and the layers are constants, stored once, whole)."""
        return tuple(name for name in OUTPUT_NAMES if not (name == "sh" and self.sh_passes))

    def _part(self, p: int, time: torch.Tensor) -> tuple:
        """The outputs of rows [a, b) of part p: the field on its moving rows, the frozen rows
        beside them (NeHaDModel.gaussians_at with the time a tensor, a graph input)."""
        a, b, num_moving, split = self._parts[p]
        g = self.model.gaussians
        out = None
        if num_moving:
            i = getattr(self, f"moving_{p}")
            out = self.deform(g.means[i], g.log_scales[i], g.quats[i], g.opacity_logits[i],
                              torch.cat([g.sh_dc[i], g.sh_rest[i]], 1), g.mu_eq[i], g.t_eq[i],
                              time, g.life_rate[i] if g.has_life() else None,
                              g.drift_velocity()[i] if g.drifts() else None, rows=i)
        if split:
            inverse = getattr(self, f"inverse_{p}")
            frozen = [getattr(self, f"frozen_{name}_{p}") for name in OUTPUT_NAMES]
            merged = [f if out is None else torch.cat([o, f], 0)[inverse]
                      for o, f in zip(out or [None] * 4, frozen[:4])]
            sh = (self.sh_all[a:b] if self.sh_passes else frozen[4] if out is None
                  else torch.cat([out[4], frozen[4]], 0)[inverse])
            out = tuple(merged) + (sh,)
        return out + (self.layer[a:b],) if self.with_layer else out

    def forward(self, time: torch.Tensor):
        parts = [self._part(p, time) for p in range(self.parts)]
        if len(parts) == 1:
            return parts[0]
        own = len(self.part_names)  # the first `own` outputs of a part are its own outputs
        whole = tuple(torch.cat(columns, 0) for columns in zip(*(part[:own] for part in parts)))
        if own < len(OUTPUT_NAMES):
            whole = whole + (self.sh_all,)
        if self.with_layer:
            whole = whole + (self.layer,)
        return whole + tuple(o for part in parts for o in part[:own])


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


__all__ = ["ExportGraph", "LAYER_OUTPUT", "MIN_PART_ROWS", "OUTPUT_NAMES", "closed_form_copy",
           "part_bounds", "reference_outputs"]
