"""The NeHaD deformation field (paper Sec. 4 and Alg. 1; docs/design.md section 4 steps 1-9).

`DeformationField(cfg, aabb, extent)(means, log_scales, quats, t, mu_eq, t_eq)` maps canonical
Gaussians to their deformed state at time t in [0, 1].
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Optional, Union

import torch
from torch import nn

from nehad.field._trace import is_capturing
from nehad.field.adapters import Adapters
from nehad.field.bed import position_mask, scale_mask
from nehad.field.config import HNN_GRAD_MODES, FieldConfig
from nehad.field.hexplane import HexPlane, normalize_aabb
from nehad.field.hnn import DirectFieldDecoder, HamiltonianDecoder
from nehad.field.mlp_decoder import MLPHeads
from nehad.field.rigidity import clamp_rotation_delta, quat_multiply, safe_normalize
from nehad.field.rigidity_kernel import clamped_rotation, fused_rotation_supported
from nehad.field.trunk import Trunk

TimeLike = Union[float, torch.Tensor]


@dataclass
class DeformedGaussians:
    """Deformed attributes at one time. `quats` are unit for the HNN decoder and r + dr
    (unnormalised, normalised at render time as 4DGS does) for the MLP decoder. Opacity logits and
    SH are the inputs passed through (or deformed, with `deform_opacity_sh`). `aux` holds
    intermediate per-Gaussian tensors for visualisation and tests: "h", "v", "v_c", "v_s", "dmu",
    "ds", "q", "force", "m_pos", "m_scale", "phi", "phi_clamped" (those that were computed)."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: Optional[torch.Tensor] = None
    sh: Optional[torch.Tensor] = None
    aux: dict[str, torch.Tensor] = field(default_factory=dict)


def time_column(t: TimeLike, n: int, like: torch.Tensor) -> torch.Tensor:
    """t as an (N, 1) column: a float / one-element tensor is broadcast, (N,) or (N, 1) kept."""
    if isinstance(t, torch.Tensor):
        t = t.to(dtype=like.dtype, device=like.device)
    else:
        t = torch.tensor(float(t), dtype=like.dtype, device=like.device)
    if not is_capturing():  # (shape checks would be baked into a traced graph as constants)
        size = math.prod(t.shape)
        if size not in (1, n):
            raise ValueError(f"DeformationField: time has {size} elements; expected 1 or N = {n}")
    return t.reshape(-1, 1).expand(n, 1)


class DeformationField(nn.Module):
    """Hex-plane encoder + trunk + decoder (docs/design.md section 4).

    Args:
        cfg: FieldConfig (validated here).
        aabb: (2, 3) box [[min], [max]] mapped to [-1, 1]^3 for the hex-plane (a buffer; see
            `set_aabb`).
        extent: scene extent; sigma_s = cfg.sigma_s_fraction * extent (a buffer).

    HNN decoder, in order (docs/design.md section 4):
      1. f = HexPlane(normalize_aabb(mu), 2t - 1) of the CANONICAL mean mu;
      2. h = M(f);
      3-4. v_c = grad_h F1, v_s = (grad_h F2) M^T, v = v_c + v_s;
           use_hnn=False: v_c, v_s are two direct MLP outputs (see FieldConfig.use_hnn);
      5. dmu = A_mu v, ds = A_s v, q = (1, 0, 0, 0) + A_r v, force F = A_mu' v_c;
      6. Verlet: mu~ = mu + dt dmu + dt^2/2 F;   verlet=False: mu~ = mu + dt dmu;
      7. BED masks from the canonical mu, mu_eq, t, t_eq (nehad.field.bed);
           mu' = mu~ (1 - M_pos) + mu M_pos, written as mu + (mu~ - mu)(1 - M_pos) (equal,
           and exact at zero displacement);   bed_position=False: mu' = mu~;
           s' = s + ds (1 - M_scale);   bed_scale=False: s' = s + ds;
      8. rigidity: dr' = clamp(q) (phi' = phi_max tanh(phi / phi_max)), r' = N(r (x) dr');
           rigidity=False: r' = N(r (x) q) (unclamped; N makes q's scale irrelevant);
      9. opacity, SH passed through; deform_opacity_sh: o' = o + A_o v, c' = c + A_c v.
    MLP decoder (4DGS baseline): mu' = mu + dmu, s' = s + ds, r' = r + dr (+ o, c with the flag);
    no BED, Verlet or clamp; mu_eq / t_eq are ignored.
    A fresh field (zero-initialised adapters / last layers) is the identity for every t.
    """

    def __init__(self, cfg: FieldConfig, aabb, extent: float = 1.0):
        super().__init__()
        self.cfg = dataclasses.replace(cfg).validate()  # own copy: later edits of `cfg` don't leak
        self.hexplane = HexPlane(cfg.out_dim, cfg.resolution, cfg.multires, cfg.plane_init_low,
                                 cfg.plane_init_high, cfg.time_plane_init)
        self.hexplane.kernel = cfg.hexplane_kernel
        self.hexplane.mipmap_levels = cfg.mipmap_levels  # used only with cfg.mipmap (docs/design.md section 8)
        self.trunk = Trunk(self.hexplane.feature_dim, cfg.width, cfg.depth)
        if cfg.decoder == "mlp":
            self.field = None
            self.adapters = None
            self.heads = MLPHeads(cfg.width, cfg.deform_opacity_sh, cfg.sh_coeffs)
        else:
            if cfg.use_hnn:
                self.field = HamiltonianDecoder(cfg.width, cfg.hnn_hidden, cfg.hnn_depth,
                                                cfg.activation, cfg.hnn_grad, cfg.hnn_init_gain,
                                                cfg.hnn_quadratic)
            else:
                self.field = DirectFieldDecoder(cfg.width, cfg.hnn_hidden, cfg.hnn_depth,
                                                cfg.activation, cfg.hnn_init_gain)
            self.adapters = Adapters(cfg.width, cfg.deform_opacity_sh, cfg.sh_coeffs)
            self.heads = None
        self.register_buffer("aabb", torch.zeros(2, 3))
        self.register_buffer("extent", torch.tensor(float(extent)))
        self.set_aabb(aabb)

    # ------------------------------------------------------------------ set-up helpers
    def set_aabb(self, aabb) -> None:
        """Set the hex-plane box (2, 3); max must exceed min on every axis."""
        box = torch.as_tensor(aabb, dtype=self.aabb.dtype).reshape(2, 3)
        if not bool(torch.all(box[1] > box[0])):
            raise ValueError(f"DeformationField.aabb: max must exceed min on every axis, got "
                             f"{box.tolist()}")
        self.aabb.copy_(box)

    def set_grad_mode(self, mode: str) -> None:
        """Switch the HNN input gradient between "autograd", "closed_form" (export) and
        "fused" (FieldConfig.hnn_grad)."""
        if isinstance(self.field, HamiltonianDecoder):
            if mode not in HNN_GRAD_MODES:
                raise ValueError(f"DeformationField.set_grad_mode: unknown mode {mode!r}")
            self.field.grad_mode = mode

    @torch.no_grad()
    def standardize_trunk(self, means: torch.Tensor, t: float, log_scales=None, quats=None,
                          target_std: float = 1.0) -> None:
        """Data-dependent initialisation of the trunk's first Linear (docs/training.md): rescale
        its rows and set its bias so that, over the given canonical Gaussians at time t, every
        channel of h has mean 0 and standard deviation `target_std`.

        With the hex-plane's initial features (a product of three planes drawn from U(0.1, 0.5),
        about 0.03 per channel) the default initialisation gives an h that is mostly the trunk's
        bias, the same for every Gaussian, so v = grad_h F(h) is too: the first gradient steps
        then learn one deformation shared by all Gaussians. Standardised, h differs between
        Gaussians by O(1) from the first step. Only the first Linear changes; it is a change of
        initial values, not of the model."""
        first = self.trunk[0]
        aabb = self.aabb.to(means.dtype)
        t_col = time_column(t, means.shape[0], means)
        sigma = None
        if self.cfg.mipmap and log_scales is not None and quats is not None:
            from nehad.field.mipmap import world_axis_sigma

            sigma = world_axis_sigma(log_scales, quats, self.cfg.norm_eps) * (
                2.0 / (aabb[1] - aabb[0]))
        f = self.hexplane(normalize_aabb(means, aabb), 2.0 * t_col - 1.0, sigma)
        raw = f @ first.weight.t()
        mean, std = raw.mean(0), raw.std(0).clamp_min(1e-8)
        gain = target_std / std
        first.weight.mul_(gain[:, None])
        first.bias.copy_(-mean * gain)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """{"grid": hex-plane planes, "decoder": trunk, F1/F2 (or heads) and adapters}; the
        trainer gives them different learning rates (docs/design.md section 5: grid 1.6e-3 -> 1.6e-4, decoder
        1e-3)."""
        grid = list(self.hexplane.parameters())
        ids = {id(p) for p in grid}
        return {"grid": grid, "decoder": [p for p in self.parameters() if id(p) not in ids]}

    def regularization_terms(self) -> dict[str, torch.Tensor]:
        """Hex-plane regularisers of 4DGS (docs/design.md section 5), unweighted."""
        space, time, l1 = self.hexplane.regularisers(self.cfg.spatial_regularizer)
        return {"plane_smoothness": space, "time_smoothness": time, "time_l1": l1}

    def regularization_loss(self) -> torch.Tensor:
        """Weighted sum of `regularization_terms()` with the cfg.reg_*_weight values."""
        r = self.regularization_terms()
        c = self.cfg
        return (c.reg_plane_weight * r["plane_smoothness"]
                + c.reg_time_smoothness_weight * r["time_smoothness"]
                + c.reg_time_l1_weight * r["time_l1"])

    # ------------------------------------------------------------------ forward
    def features(self, means: torch.Tensor, t_col: torch.Tensor,
                 log_scales: Optional[torch.Tensor] = None,
                 quats: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Step 1-2: h = M(HexPlane(normalize_aabb(mu), 2t - 1)), (N, W). With cfg.mipmap the
        lookups are mipmapped by the canonical Gaussians' world-axis scales (docs/design.md section 8), which
        then need `log_scales` and `quats`."""
        return self.trunk(self.plane_features(means, t_col, log_scales, quats))

    def plane_features(self, means: torch.Tensor, t_col: torch.Tensor,
                       log_scales: Optional[torch.Tensor] = None,
                       quats: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Step 1: f = HexPlane(normalize_aabb(mu), 2t - 1), the trunk's input (`features`)."""
        aabb = self.aabb.to(means.dtype)
        sigma = None
        if self.cfg.mipmap:
            if log_scales is None or quats is None:
                raise ValueError("DeformationField.features: field.mipmap needs the Gaussians' "
                                 "log_scales and quats")
            from nehad.field.mipmap import world_axis_sigma

            sigma = world_axis_sigma(log_scales, quats, self.cfg.norm_eps) * (
                2.0 / (aabb[1] - aabb[0]))
        return self.hexplane(normalize_aabb(means, aabb), 2.0 * t_col - 1.0, sigma)

    def forward(self, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                t: TimeLike, mu_eq: Optional[torch.Tensor] = None,
                t_eq: Optional[torch.Tensor] = None, opacity_logits: Optional[torch.Tensor] = None,
                sh: Optional[torch.Tensor] = None) -> DeformedGaussians:
        """Deform canonical Gaussians (means (N, 3), log_scales (N, 3), quats (N, 4) wxyz) to time
        t (float, one-element tensor, or (N,)/(N, 1)). mu_eq (N, 3) and t_eq (N, 1) are required
        when BED position (mu_eq, t_eq) or BED scale (t_eq) is on with the HNN decoder."""
        n = means.shape[0]
        t_col = time_column(t, n, means)
        if self.cfg.decoder == "mlp":
            h = self.features(means, t_col, log_scales, quats)
            return self._forward_mlp(h, means, log_scales, quats, opacity_logits, sh)
        cfg = self.cfg
        fo, ad, force, h = self._decode(self.plane_features(means, t_col, log_scales, quats))
        aux: dict[str, torch.Tensor] = {"dmu": ad.dmu, "ds": ad.ds, "q": ad.q}
        if fo is not None:  # the fused decoder does not form v (HamiltonianDecoder.fused_features)
            aux.update(v=fo.v, v_c=fo.v_c, v_s=fo.v_s)
        if h is not None:
            aux["h"] = h
        # 6. position Verlet: displacement mu~ - mu.
        disp = cfg.dt * ad.dmu
        if cfg.verlet:
            aux["force"] = force
            disp = disp + (0.5 * cfg.dt * cfg.dt) * force
        # 7. Boltzmann equilibrium blending.
        if self.reads("t_eq"):
            if t_eq is None or (self.reads("mu_eq") and mu_eq is None):
                raise ValueError("DeformationField.forward: mu_eq and t_eq are required with "
                                 "bed_position / bed_scale on")
            t_eq = t_eq.reshape(n, 1)
        if cfg.bed_position:
            at = means + disp if cfg.bed_distance == "deformed" else means
            m_pos = position_mask(at, mu_eq, t_col, t_eq,
                                  sigma_s=cfg.sigma_s_fraction * self.extent.to(means.dtype),
                                  sigma_t=cfg.sigma_t, beta=cfg.beta, gamma=cfg.gamma,
                                  lam=cfg.lam, eps=cfg.norm_eps, floor=cfg.bed_floor)
            aux["m_pos"] = m_pos
            disp = disp * (1.0 - m_pos)
        new_means = means + disp
        ds = ad.ds
        if cfg.bed_scale:
            m_scale = scale_mask(t_col, t_eq, sigma_t=cfg.sigma_t, beta=cfg.beta, gamma=cfg.gamma,
                                 floor=cfg.bed_floor)
            aux["m_scale"] = m_scale
            ds = ds * (1.0 - m_scale)
        new_log_scales = log_scales + ds
        # 8. rotation: rigidity clamp of the quaternion delta, then r' = N(r (x) dr').
        new_quats = self._rotate(quats, ad.q, aux)
        # 9. appearance.
        new_o, new_sh = self._appearance(opacity_logits, sh, ad.d_opacity, ad.d_sh)
        return DeformedGaussians(new_means, new_log_scales, new_quats, new_o, new_sh, aux)

    def reads(self, name: str) -> bool:
        """Whether `forward` reads its optional input `name` under this config: "mu_eq" (BED's
        position mask), "t_eq" (either BED mask), "appearance" (the opacity logits and SH it
        deforms); where it does not, the caller may pass None."""
        cfg = self.cfg
        return {"mu_eq": cfg.bed_position, "t_eq": cfg.bed_position or cfg.bed_scale,
                "appearance": cfg.deform_opacity_sh}[name]

    def _rotate(self, quats: torch.Tensor, q: torch.Tensor, aux: dict) -> torch.Tensor:
        """Step 8: r' = N(r (x) dr'), dr' the rigidity clamp of the raw delta q (or q itself
        with `rigidity` off); the angles phi, phi' go to `aux`."""
        cfg = self.cfg
        if cfg.rigidity and self._rotation_fused(quats, q):  # the same in one Numba pass
            new_quats, aux["phi"], aux["phi_clamped"] = clamped_rotation(
                quats, q, cfg.phi_max, cfg.norm_eps)
            return new_quats
        dr = q
        if cfg.rigidity:
            rd = clamp_rotation_delta(q, cfg.phi_max, cfg.norm_eps)
            dr = rd.dr
            aux["phi"], aux["phi_clamped"] = rd.phi, rd.phi_clamped
        return safe_normalize(quat_multiply(quats, dr), cfg.norm_eps)

    def _rotation_fused(self, quats: torch.Tensor, q: torch.Tensor) -> bool:
        """Whether step 8 runs as `nehad.field.rigidity_kernel`'s pass (`rotation_kernel`
        "numba", CPU float tensors, no graph being captured)."""
        return (self.cfg.rotation_kernel == "numba" and not is_capturing()
                and fused_rotation_supported(quats, q))

    def _decode(self, f: torch.Tensor):
        """Steps 2-5 on the plane features f: (FieldOutput, AdapterOutput, force, h). With the
        Hamiltonian decoder and a one-layer trunk, trunk, decoder and adapters run as one fused
        call where they can (`HamiltonianDecoder.fused_features`), which gives neither the
        FieldOutput nor h (None)."""
        if isinstance(self.field, HamiltonianDecoder) and self.trunk.depth == 1:
            fused = self.field.fused_features(f, self.trunk[0], self.adapters)
            if fused is not None:
                return (*fused, None)
        h = self.trunk(f)
        fo = self.field(h)
        force = self.adapters.force(fo.v_c) if self.cfg.verlet else None
        return fo, self.adapters(fo.v), force, h

    def _forward_mlp(self, h, means, log_scales, quats, opacity_logits, sh) -> DeformedGaussians:
        d = self.heads(h)
        new_o, new_sh = self._appearance(opacity_logits, sh, d["d_opacity"], d["d_sh"])
        aux = {"h": h, "dmu": d["dmu"], "ds": d["ds"], "dr": d["dr"]}
        return DeformedGaussians(means + d["dmu"], log_scales + d["ds"], quats + d["dr"],
                                 new_o, new_sh, aux)

    def _appearance(self, opacity_logits, sh, d_o, d_sh):
        """(opacity logits, SH) at t: passed through, or deformed with `deform_opacity_sh`.
        A caller that asks for the geometry only (neither given: the motion priors, the
        positions of some rows) gets (None, None)."""
        if d_o is None or (opacity_logits is None and sh is None):
            return opacity_logits, sh
        if opacity_logits is None or sh is None:
            raise ValueError("DeformationField.forward: deform_opacity_sh needs opacity_logits "
                             "and sh together")
        k = sh.shape[1]
        if k > self.cfg.sh_coeffs:
            raise ValueError(f"DeformationField.forward: sh has {k} coefficients per channel, "
                             f"more than cfg.sh_coeffs = {self.cfg.sh_coeffs}")
        return opacity_logits + d_o.reshape(opacity_logits.shape), sh + d_sh[:, :k]


__all__ = ["DeformationField", "DeformedGaussians", "time_column"]
