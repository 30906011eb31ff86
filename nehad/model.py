"""The model of a run, apart from its training: canonical Gaussians plus the deformation field
(`NeHaDModel`), the one way a model is rebuilt from a saved state (`load_run`,
`model_from_state`), what a run records beside its tensors (`RunInfo`) and its Gaussians at a
time for the shared rasterizer (`cloud_at`). Evaluation, inspection and export import this
module, not the trainer."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field as dataclass_field
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from nehad.checkpoint import RunError, load_state
from nehad.config import config_from_dict
from nehad.field.deformation import DeformationField, DeformedGaussians, time_column
from nehad.gaussians import GaussianParameters


class NeHaDModel(torch.nn.Module):
    """Canonical Gaussians + deformation field: renders the scene at any time."""

    def __init__(self, gaussians: GaussianParameters, field: DeformationField):
        super().__init__()
        self.gaussians = gaussians
        self.field = field

    def gaussians_at(self, t, deform: bool = True):
        """Activated (means, scales, quats, opacities (N,), sh) at time t (canonical if not
        deform). t is a float or a one-element tensor (the ONNX export traces it as an input).
        The opacities carry each Gaussian's life factor at t (GaussianParameters.life_factor)
        and the means its drift (GaussianParameters.drift), deformed or not."""
        g = self.gaussians
        if not deform or t is None:
            return self._alive_at(t, *g.activated())
        sh = torch.cat([g.sh_dc, g.sh_rest], 1)
        return self._activated_at(t, self.field(g.means, g.log_scales, g.quats, t, g.mu_eq,
                                                g.t_eq, opacity_logits=g.opacity_logits, sh=sh))

    def gaussians_and_samples_at(self, t, rows: torch.Tensor, times: torch.Tensor,
                                 with_view_rows: bool = False):
        """(`gaussians_at(t)`'s tuple, the field's `DeformedGaussians` of the Gaussians `rows`
        (M,), row i at time times[i]) from ONE field evaluation of N + M rows: the motion priors'
        samples ride on the view's evaluation (`nehad.motion_priors`), where a call of their own
        costs the field's fixed costs again (docs/performance.md). Each row is deformed on its
        own, so both parts equal separate calls' to rounding. `with_view_rows`: the second part
        is 2M rows, the view's own rows `rows` at t first (no second evaluation of them)."""
        g = self.gaussians
        n = g.means.shape[0]
        index = torch.cat([torch.arange(n), rows.to(torch.int64)])

        def more(x, needed=True):
            """x's rows, then x's `rows` again (one gather; its backward one scatter-add). The
            inputs the field does not read (opacities and SH it does not deform, the
            equilibria without BED) are not copied: None."""
            return x.index_select(0, index) if needed else None

        sh = torch.cat([g.sh_dc, g.sh_rest], 1)
        t_col = torch.cat([time_column(t, n, g.means),
                           times.to(dtype=g.means.dtype).reshape(-1, 1)])
        reads = self.field.reads
        appearance = reads("appearance")
        out = self.field(more(g.means), more(g.log_scales), more(g.quats), t_col,
                         more(g.mu_eq, reads("mu_eq")), more(g.t_eq, reads("t_eq")),
                         opacity_logits=more(g.opacity_logits, appearance),
                         sh=more(sh, appearance))
        head = DeformedGaussians(out.means[:n], out.log_scales[:n], out.quats[:n],
                                 out.opacity_logits[:n] if appearance else g.opacity_logits,
                                 out.sh[:n] if appearance else sh)
        if with_view_rows:
            tail = DeformedGaussians(*(torch.cat([x[:n][rows], x[n:]])
                                       for x in (out.means, out.log_scales, out.quats)))
        else:
            tail = DeformedGaussians(out.means[n:], out.log_scales[n:], out.quats[n:])
        return self._activated_at(t, head), tail

    def _activated_at(self, t, out):
        """`gaussians_at`'s tuple from the field's output for every Gaussian at t."""
        quats = out.quats / out.quats.norm(dim=-1, keepdim=True)
        opacities = torch.sigmoid(out.opacity_logits).reshape(out.means.shape[0])
        return self._alive_at(t, out.means, torch.exp(out.log_scales), quats, opacities, out.sh)

    def _alive_at(self, t, means, scales, quats, opacities, sh):
        """The activated Gaussians with each one's life factor and drift at t applied."""
        g = self.gaussians
        life, drift = g.life_factor(t), g.drift(t)
        if life is not None:
            opacities = opacities * life
        if drift is not None:
            means = means + drift
        return means, scales, quats, opacities, sh

    def means_at(self, t: float, rows: torch.Tensor) -> torch.Tensor:
        """The deformed means (with their drift) at time t of the Gaussians `rows` only, as
        `gaussians_at` gives them (the field deforms each Gaussian on its own)."""
        g = self.gaussians
        out = self.field(g.means[rows], g.log_scales[rows], g.quats[rows], t, g.mu_eq[rows],
                         g.t_eq[rows])
        drift = g.drift(t)
        return out.means if drift is None else out.means + drift[rows]


def cloud_at(model: NeHaDModel, t: float | None, sh_degree: int):
    """The activated Gaussians of a run at time t as a `GaussianCloud` (canonical if t is None),
    for the shared rasterizer."""
    from nehad.runtime.gaussians import GaussianCloud

    with torch.no_grad():
        params = model.gaussians_at(t, deform=t is not None)
    means, scales, quats, opac, sh = (p.detach().cpu().numpy() for p in params)
    return GaussianCloud(means, scales, quats, opac, sh[:, :(sh_degree + 1) ** 2])


@dataclass(frozen=True)
class RunInfo:
    """What RUN/model.pt records beside the model's tensors (written by
    `nehad.trainer.Trainer.model_state`); every reader of a run takes it from here. A model built
    by hand (tests, benchmarks) gives what it knows; the rest keeps the defaults below."""

    sh_degree: int | None = None
    """The SH degree the run renders with (None: the model's full degree)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    time_range: tuple[float, float] = (0.0, 1.0)
    config_dict: dict | None = None
    """The run's configuration as saved (`config` gives it as a Config)."""
    data_dir: str | None = None
    """The dataset the run was trained on (absolute path), if recorded."""
    steps: int | None = None
    extent: float | None = None
    aabb: np.ndarray | None = None
    """(2, 3) hex-plane box at the end of training."""
    layer: np.ndarray | None = None
    """(N,) int32 streaming layer of each Gaussian (None: trained without layers)."""
    lod: dict = dataclass_field(default_factory=dict)
    """The layered schedule's record (`nehad.lod.LayeredSchedule.model_extras`)."""

    @classmethod
    def from_state(cls, state: dict) -> "RunInfo":
        """From a saved RUN/model.pt state (its entries other than the tensors)."""
        def array(key, dtype):
            v = state.get(key)
            if v is None:
                return None
            return np.asarray(v.cpu().numpy() if torch.is_tensor(v) else v, dtype)

        return cls(
            sh_degree=None if state.get("sh_degree") is None else int(state["sh_degree"]),
            background=tuple(float(v) for v in state.get("background", (0.0, 0.0, 0.0))),
            time_range=tuple(float(v) for v in (state.get("time_range") or (0.0, 1.0))),
            config_dict=state.get("config"), data_dir=state.get("data_dir"),
            steps=None if state.get("steps") is None else int(state["steps"]),
            extent=None if state.get("extent") is None else float(state["extent"]),
            aabb=array("aabb", np.float64), layer=array("layer", np.int32),
            lod=dict(state.get("lod") or {}))

    @cached_property
    def config(self):
        """The run's configuration as a `nehad.config.Config` (None if not recorded)."""
        return None if self.config_dict is None else config_from_dict(self.config_dict)

    def degree_for(self, model: "NeHaDModel") -> int:
        """The SH degree to render `model` with: the recorded one, else the model's own."""
        return model.gaussians.sh_degree if self.sh_degree is None else int(self.sh_degree)

    def replace(self, **changes) -> "RunInfo":
        return dataclasses.replace(self, **changes)


def load_run(run_dir) -> tuple[NeHaDModel, RunInfo]:
    """Load RUN/model.pt as a model plus what the run records beside it (`RunInfo`)."""
    run = Path(run_dir)
    path = run / "model.pt"
    if not path.exists():
        raise RunError(f"{run}: no model.pt (training not finished?)")
    state = load_state(path)
    try:
        model = model_from_state(state)
    except (RuntimeError, KeyError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise RunError(f"{path}: its tensors do not fit its config ({first})") from None
    return model, RunInfo.from_state(state)


def model_from_state(state: dict) -> NeHaDModel:
    """The model (in eval mode) of a saved state: RUN/model.pt or a checkpoint (the field's box
    and extent are buffers of its state dict, so both kinds rebuild the same way)."""
    cfg = config_from_dict(state["config"])
    gaussians = GaussianParameters.empty_like_state(state["gaussians"])
    gaussians.load_state_dict(GaussianParameters.with_defaults(state["gaussians"]))
    field = DeformationField(cfg.field, state["field"]["aabb"], float(state["field"]["extent"]))
    field.load_state_dict(state["field"])
    gaussians.drift_window = float(cfg.train.drift_window)
    return NeHaDModel(gaussians, field).eval()


__all__ = ["NeHaDModel", "RunError", "RunInfo", "cloud_at", "load_run", "model_from_state"]
