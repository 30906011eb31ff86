"""Gaussians that do not move, found at export and written pre-deformed (issue 27).

Most of a scene is still, yet every Gaussian goes through the deformation field at every frame.
`find_static` samples the model on a dense time grid (the hex-plane's time knots and `per_cell`
times between each pair, so the grid sees every cell of the time axis) and calls a Gaussian
static when, over the whole grid, none of its rendered attributes leaves the value it has at the
grid time nearest the canonical time by more than the bounds of :class:`StaticBounds`. Its
outputs at that time are then constants of the exported graph, and the field runs on the other
Gaussians only (:class:`nehad.export.graph.ExportGraph`); the graph's outputs keep the model's
order. The bounds keep a frame above 60 dB PSNR of the unsplit model's (measured) (docs/usage.md, "Export"; tests/test_static_split.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class StaticBounds:
    """Largest change over time that still counts as static."""

    # Measured on the stress suite's occluder (docs/results.md, 2026-11-25): at these bounds
    # 49% of its Gaussians are static and every test frame stays 61.8 dB from the unsplit
    # model's; at 1e-4 / 1e-3 none was.
    position: float = 1e-3  # of the scene extent (the camera rig's radius, docs/design.md 4.7)
    log_scale: float = 1e-2  # in log-scale (1% of the size)
    rotation: float = 1e-2  # radians
    opacity: float = 1e-4  # and each SH coefficient


@dataclass
class StaticSplit:
    """`mask` [N] bool: the static Gaussians; `frozen`: their (means, scales, quats, opacities, sh)
    at time `time` (sh: the first k coefficients); `deviation`: the largest change over the grid
    among them, per attribute (position as a fraction of the extent)."""

    mask: np.ndarray
    frozen: tuple
    time: float
    times: int
    deviation: dict

    @property
    def num_static(self) -> int:
        return int(self.mask.sum())

    def apply(self, outputs: list) -> list:
        """`outputs` (the model's, in OUTPUT_NAMES order, NumPy) with the static rows replaced by
        their frozen values: what the split graph computes."""
        out = [np.array(o, copy=True) for o in outputs]
        for i, value in enumerate(self.frozen):
            out[i][self.mask] = value
        return out


def time_grid(field_cfg, per_cell: int = 8) -> np.ndarray:
    """Times in [0, 1]: the time axis's knots (resolution[3] of the hex-plane) and `per_cell`
    steps within each cell."""
    cells = max(1, int(field_cfg.resolution[3]) - 1)
    return np.linspace(0.0, 1.0, cells * per_cell + 1)


def find_static(model, sh_degree: int, bounds: StaticBounds = StaticBounds(),
                per_cell: int = 8, canonical_time: float = 0.5) -> StaticSplit:
    """Sample `model.gaussians_at` on `time_grid` and split off the Gaussians that stay within
    `bounds` (module docstring). The model is only read."""
    k = (int(sh_degree) + 1) ** 2
    times = time_grid(model.field.cfg, per_cell)
    ref_t = float(times[np.argmin(np.abs(times - canonical_time))])
    extent = float(model.field.extent)

    def at(t):
        with torch.no_grad():
            means, scales, quats, opac, sh = model.gaussians_at(
                torch.tensor([t], dtype=torch.float32))
        return means, torch.log(scales), quats, opac, sh[:, :k], scales

    ref = at(ref_t)
    n = ref[0].shape[0]
    worst = {name: torch.zeros(n, dtype=torch.float64)
             for name in ("position", "log_scale", "rotation", "opacity", "sh")}
    for t in times:
        means, log_s, quats, opac, sh, _ = at(float(t))
        worst["position"] = torch.maximum(
            worst["position"], (means - ref[0]).abs().amax(1).double() / extent)
        worst["log_scale"] = torch.maximum(worst["log_scale"],
                                           (log_s - ref[1]).abs().amax(1).double())
        # the angle from the chord between the unit quaternions (acos of their dot product
        # reads float32 rounding near 1 as 1e-3 rad): angle = 4 asin(|q -+ q_ref| / 2)
        q, q0 = quats.double(), ref[2].double()
        chord = torch.minimum((q - q0).norm(dim=1), (q + q0).norm(dim=1))
        worst["rotation"] = torch.maximum(worst["rotation"],
                                          4.0 * torch.asin((chord / 2).clamp(max=1.0)))
        worst["opacity"] = torch.maximum(worst["opacity"], (opac - ref[3]).abs().double())
        worst["sh"] = torch.maximum(worst["sh"], (sh - ref[4]).abs().flatten(1).amax(1).double())
    mask = ((worst["position"] <= bounds.position) & (worst["log_scale"] <= bounds.log_scale)
            & (worst["rotation"] <= bounds.rotation) & (worst["opacity"] <= bounds.opacity)
            & (worst["sh"] <= bounds.opacity))
    if mask.all():  # the field keeps at least one Gaussian (a graph whose outputs ignore the
        mask[-1] = False  # time input would lose that input)
    mask_np = mask.numpy()
    frozen = (ref[0][mask].numpy(), ref[5][mask].numpy(), ref[2][mask].numpy(),
              ref[3][mask].numpy(), ref[4][mask].numpy())
    deviation = {name: (float(v[mask].max()) if mask.any() else 0.0)
                 for name, v in worst.items()}
    deviation = {name: (v if math.isfinite(v) else float("inf")) for name, v in deviation.items()}
    return StaticSplit(mask_np, frozen, ref_t, len(times), deviation)


__all__ = ["StaticBounds", "StaticSplit", "find_static", "time_grid"]
