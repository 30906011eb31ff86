"""Learnable canonical Gaussians in torch, stored as 3DGS stores them (docs/design.md section 3): means,
log-scales, quaternions (w, x, y, z, unnormalised), opacity logits, SH coefficients split into the
DC term and the rest (they get different learning rates), and the Boltzmann equilibrium
parameters of docs/design.md section 4.7 (mu_eq, t_eq), set when the fine stage starts, and a
life rate k >= 0: the Gaussian's opacity at time t is scaled by exp(-(k (t - t_eq))^2 / 2)
(`life_factor`; docs/training.md, "Objects that are never created"). Every Gaussian starts with
k = 0 (it lives at every time, and the gradient of k is zero there, so it stays so); residual
carving (nehad.carve) gives the Gaussians it adds a finite life around the time they were seen,
and a velocity v: over its life such a Gaussian moves in a straight line, mu + v (t - t_eq) after
the deformation field (`drift`), so that it can follow its object into the times next to the one
it was carved at (docs/training.md). A Gaussian with k = 0 never drifts, unless the run has a
drift window W > 0 (`train.drift_window`, off): then every Gaussian moves v clamp(t - t_eq,
-W, W) from the static stage on, which was meant to let the static stage fit an object that
moves across its time window; measured, it does not (docs/training.md).

Every parameter's first dimension is the Gaussian index, so densification (nehad.densify) treats
them all alike: clone, split and prune apply to each one, and children inherit mu_eq and t_eq."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

import nehad.vector_math  # noqa: F401  (MKL set up serially before any parallel call)
from nehad.neighbours import nearest_neighbours
from nehad.runtime.gaussians import SH_C0, GaussianCloud


def rgb_to_sh_dc(rgb):
    """SH DC coefficient that renders as `rgb` (rgb = C0 * dc + 0.5)."""
    return (rgb - 0.5) / SH_C0


def _nearest_neighbour_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance to the k nearest other points (3DGS scale initialisation); with k or fewer
    other points, to all of them; a lone point gets 0.01 (the scene's unit)."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    if len(pts) < 2:
        return np.full(len(pts), 0.01, np.float32)
    # distances of the float32 points, as the scales are (ties broken either way agree)
    return nearest_neighbours(pts, k)[1].mean(1).astype(np.float32)


class GaussianParameters(nn.Module):
    """N Gaussians' raw parameters; `activated()` gives what the renderer consumes."""

    NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "mu_eq", "t_eq",
             "life_rate", "velocity")
    #: The shapes one Gaussian's row of each parameter may have (the tensor is (N, *row)):
    #: sh_rest holds the (degree + 1)^2 - 1 higher SH coefficients of degree 0..3.
    ROW_SHAPES = {"means": ((3,),), "log_scales": ((3,),), "quats": ((4,),),
                  "opacity_logits": ((), (1,)), "sh_dc": ((1, 3),),
                  "sh_rest": tuple(((d + 1) ** 2 - 1, 3) for d in range(4)), "mu_eq": ((3,),),
                  "t_eq": ((1,),), "life_rate": ((1,),), "velocity": ((3,),)}

    def __init__(self, means, log_scales, quats, opacity_logits, sh_dc, sh_rest, mu_eq=None,
                 t_eq=None, life_rate=None, velocity=None):
        super().__init__()
        f32 = lambda a: torch.as_tensor(np.asarray(a) if not torch.is_tensor(a) else a,
                                        dtype=torch.float32).clone()
        self.means = nn.Parameter(f32(means))
        self.log_scales = nn.Parameter(f32(log_scales))
        self.quats = nn.Parameter(f32(quats))
        self.opacity_logits = nn.Parameter(f32(opacity_logits))
        self.sh_dc = nn.Parameter(f32(sh_dc))
        self.sh_rest = nn.Parameter(f32(sh_rest))
        n = self.means.shape[0]
        self.mu_eq = nn.Parameter(self.means.detach().clone() if mu_eq is None else f32(mu_eq))
        self.t_eq = nn.Parameter(torch.full((n, 1), 0.5) if t_eq is None else f32(t_eq))
        self.life_rate = nn.Parameter(torch.zeros(n, 1) if life_rate is None else f32(life_rate))
        self.velocity = nn.Parameter(torch.zeros(n, 3) if velocity is None else f32(velocity))
        #: train.drift_window (not a tensor: set from the run's config where the model is built)
        self.drift_window = 0.0

    @classmethod
    def empty_like_state(cls, state: dict) -> "GaussianParameters":
        """Parameters shaped like a saved state dict (to load a checkpoint into). A state saved
        before the life rate existed gets k = 0 (`with_defaults`)."""
        state = cls.with_defaults(state)
        return cls(*(torch.zeros_like(state[name]) for name in cls.NAMES))

    @staticmethod
    def with_defaults(state: dict) -> dict:
        """`state` (a state dict of these parameters) with `life_rate` and `velocity` = 0 added
        where absent (states saved before they existed); as given without a (N, ...) means."""
        if not torch.is_tensor(state.get("means")) or state["means"].dim() == 0:
            return state
        n = state["means"].shape[0]
        extra = {name: torch.zeros(n, width) for name, width in (("life_rate", 1), ("velocity", 3))
                 if name not in state}
        return {**state, **extra} if extra else state

    def mortal(self) -> torch.Tensor:
        """(N,) bool: the Gaussians with a finite life (k != 0), the tracks' chains and the
        carved ones."""
        return self.life_rate.detach().reshape(-1) != 0

    def has_life(self) -> bool:
        """Whether any Gaussian has a finite life (k != 0)."""
        return bool(self.mortal().any())

    def reset_equilibrium(self, t_eq: float = 0.5) -> None:
        """docs/design.md section 4.7: mu_eq starts as mu and t_eq at the canonical time (train.canonical_time,
        0.5 by default) when the fine stage begins."""
        with torch.no_grad():
            self.mu_eq.copy_(self.means)
            self.t_eq.fill_(float(t_eq))

    @classmethod
    def from_points(cls, points, colors=None, sh_degree: int = 3, opacity: float = 0.1,
                    seed: int = 0) -> "GaussianParameters":
        """3DGS initialisation: isotropic scales from the mean distance to 3 neighbours,
        identity rotations, opacity 0.1, colour from the points (grey if none)."""
        points = np.asarray(points, np.float32)
        n = len(points)
        if colors is None:
            colors = np.full((n, 3), 0.5, np.float32)
        dist = np.clip(_nearest_neighbour_distance(points), 1e-7, None)
        log_scales = np.repeat(np.log(dist)[:, None], 3, 1)
        quats = np.zeros((n, 4), np.float32)
        quats[:, 0] = 1
        logit = np.log(opacity / (1 - opacity))
        k = (sh_degree + 1) ** 2
        sh_dc = rgb_to_sh_dc(np.asarray(colors, np.float32))[:, None, :]
        return cls(points, log_scales, quats, np.full(n, logit, np.float32), sh_dc,
                   np.zeros((n, k - 1, 3), np.float32))

    @classmethod
    def random_in_box(cls, n: int, low=-1.3, high=1.3, sh_degree: int = 3, seed: int = 0):
        """D-NeRF initialisation: `n` random points in the cube [low, high]^3 (docs/design.md section 5)."""
        rng = np.random.default_rng(seed)
        pts = rng.uniform(low, high, (n, 3)).astype(np.float32)
        return cls.from_points(pts, rng.uniform(0, 1, (n, 3)).astype(np.float32), sh_degree)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1

    def activated(self):
        """(means, scales, unit quats, opacities, sh (N, K, 3))."""
        quats = self.quats / self.quats.norm(dim=-1, keepdim=True)
        return (self.means, torch.exp(self.log_scales), quats, torch.sigmoid(self.opacity_logits),
                torch.cat([self.sh_dc, self.sh_rest], 1))

    def life_factor(self, t) -> torch.Tensor | None:
        """(N,) the opacity factor exp(-(k (t - t_eq))^2 / 2) at time t, or None when every
        Gaussian lives at every time (k = 0: the factor is 1)."""
        if t is None or not self.has_life():
            return None
        t = torch.as_tensor(t, dtype=self.t_eq.dtype).reshape(())
        return torch.exp(-0.5 * (self.life_rate * (t - self.t_eq)).square()).reshape(-1)

    def drifts(self) -> bool:
        """Whether any Gaussian can drift (a drift window, or a finite life)."""
        return self.drift_window > 0 or self.has_life()

    def drift(self, t) -> torch.Tensor | None:
        """(N, 3) the straight-line motion after the field, or None when nothing drifts: with a
        drift window W, v clamp(t - t_eq, -W, W) for every Gaussian; without, v (t - t_eq) for
        the Gaussians with a finite life (a carved Gaussian follows its object over its life;
        nehad.carve) and 0 for the others (their velocity's gradient is masked, so it stays 0)."""
        if t is None or not self.drifts():
            return None
        t = torch.as_tensor(t, dtype=self.t_eq.dtype).reshape(())
        dt = t - self.t_eq
        if self.drift_window > 0:
            dt = dt.clamp(-self.drift_window, self.drift_window)
        return self.drift_velocity() * dt

    def drift_velocity(self) -> torch.Tensor:
        """(N, 3) the velocities that drift: every Gaussian's with a drift window, else those of
        the Gaussians with a finite life and 0 for the others."""
        if self.drift_window > 0:
            return self.velocity
        return self.velocity * self.mortal()[:, None].to(self.velocity.dtype)

    def to_cloud(self) -> GaussianCloud:
        with torch.no_grad():
            means, scales, quats, opac, sh = (t.detach().cpu().numpy() for t in self.activated())
        return GaussianCloud(means, scales, quats, opac, sh)
