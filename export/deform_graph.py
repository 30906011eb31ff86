"""The deformation as it is written into the exported graph (docs/design.md section 4 and 7), arranged for
onnxruntime.

`FastDeform(model, sh_degree)(arrays, time)` computes what `NeHaDModel.gaussians_at(t)` computes
(activated means, scales, unit quats, opacities, SH truncated to `sh_degree`) for canonical
Gaussians given as arrays, with the same parameters, rearranged so that onnxruntime runs few
operators over all N Gaussians: it does not fuse elementwise chains, so every full-width
(N, 32..128) Mul/Add is a pass over memory. Per call (after onnxruntime's constant folding) the
single-file graph runs ~170 nodes: 6 Gathers and 9 elementwise ops of the hex-plane, 6 GEMMs
(N, 64) and 8 elementwise ops of the decoder, and a tail on (k, N) rows.

Rearrangements (each exact in real arithmetic; the export checks parity against the torch model,
docs/design.md section 7):

* Hex-plane (docs/design.md section 4.1). Only the space-time planes depend on t. The product of the three spatial
  planes depends on the canonical Gaussians only: in the single-file export it is a constant
  subgraph (GridSample) that onnxruntime folds once when the session is created, so the file
  does not grow; with mipmapping it is computed here and stored (see `FastDeform`). A space-time
  plane at time t is first sliced: its two rows around t interpolated into a small (R, C) table
  (`time_rows`), then sampled by 1-D linear interpolation along its spatial axis, A[i] + f D[i]
  (2 Gathers instead of the 4 of a bilinear lookup). The scales are stacked into one table per
  axis, so one Gather serves all scales. With mipmapping (docs/design.md section 8) every level is sliced the same
  way and the two levels around l_hat are blended.
* HNN decoder (docs/design.md section 4.3-4.6). The closed-form input gradient of each scalar net ends with W1^T;
  v_s = (grad F2) M^T, the adapters, the Verlet step dmu dt + F dt^2/2 and the force adapter are
  all linear in (grad F1, grad F2). So everything the adapters produce is
  delta1(F1) @ P1 + delta1(F2) @ P2 with precomposed P1, P2 (biases folded): one small GEMM per
  net. The last trunk Linear is folded into the first layer of F1 and F2 (h itself is not an
  output), and the output weight w_out of each net into its last layer's backward matrix; for
  tanh, act'(z) @ M = colsum(M) - (a * a) @ M is one Gemm.
* MLP decoder (4DGS baseline). The first Linear of every head runs as one GEMM, the last layers
  as one block-diagonal GEMM.
* Tail (BED masks, rigidity clamp, quaternion product; the training code's functions with
  dim=0) on (k, N) rows: onnxruntime broadcasts (N, 1) against a scalar or (N, 3) against (N, 1)
  about 40x slower than (1, N) against a scalar or (3, N) against (1, N).
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nehad.field.bed import position_mask, scale_mask
from nehad.field.hexplane import (PLANE_AXES, SPACE_PLANES, TIME_PLANES, bilinear_gather,
                                  normalize_aabb)
from nehad.field.hnn import HamiltonianDecoder, activation_with_derivative
from nehad.field.hnn_fused import symplectic_transpose
from nehad.field.rigidity import clamp_rotation_delta, quat_multiply, safe_normalize

# ---------------------------------------------------------------------------- hex-plane (4.1)


def lerp_index(x: torch.Tensor, r) -> tuple[torch.Tensor, torch.Tensor]:
    """(i0, frac) of align_corners=True, border-clamped linear interpolation of coordinates x in
    [-1, 1] over r samples (r an int or a tensor like x): i0 <= r - 2 so i0 + 1 is valid (as
    `bilinear_gather`)."""
    if isinstance(r, int):
        p = ((x + 1.0) * (0.5 * (r - 1))).clamp(0.0, r - 1.0)
        i0 = p.floor().clamp(max=max(r - 2, 0))
    else:  # per-point sizes (mip levels), as PlanePyramid.sample
        p = torch.minimum(((x + 1.0) * (0.5 * (r - 1.0))).clamp(min=0.0), r - 1.0)
        i0 = torch.minimum(p.floor(), (r - 2.0).clamp(min=0.0))
    return i0, p - i0


def time_rows(table: torch.Tensor, tp: torch.Tensor) -> torch.Tensor:
    """A space-time plane given as (T, R, C) (time, space, channels) at time tp (1,) in [-1, 1]:
    its two rows around tp interpolated, (R, C)."""
    rows = table.shape[0]
    t0, ft = lerp_index(tp, rows)
    i = t0.to(torch.int64)
    r0 = table.index_select(0, i)[0]
    r1 = table.index_select(0, i + (1 if rows > 1 else 0))[0]
    return r0 * (1.0 - ft) + r1 * ft


def with_differences(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(A, D) for a (R, C) table: D[i] = A[i + 1] - A[i] (last row 0), so that linear
    interpolation at i0 + f is A[i0] + f D[i0] (two Gathers, one Mul, one Add)."""
    zero = torch.zeros_like(rows[:1])
    return rows, torch.cat([rows[1:] - rows[:-1], zero], 0)


def space_time_term(a_tab: torch.Tensor, d_tab: torch.Tensor, idx: torch.Tensor,
                    frac: torch.Tensor) -> torch.Tensor:
    """A[idx] + frac D[idx]: idx (N, S) rows of the stacked tables, frac (N, S, 1) -> (N, S, C)."""
    return a_tab[idx] + frac * d_tab[idx]


def plane_table(plane: torch.Tensor) -> torch.Tensor:
    """A (1, C, T, R) space-time plane as a (T, R, C) table."""
    return plane[0].permute(1, 2, 0)


def spatial_features(hexplane, x: torch.Tensor, constant: bool) -> torch.Tensor:
    """Product of the spatial planes xy, xz, yz per scale, (N, S, C). With `constant` (x is
    built from initializers only, so onnxruntime folds this once at session creation) as
    GridSample: one node and one (C, N) result per plane, where the bilinear Gathers leave ~10
    (N, C) intermediates per plane that the folding holds until it ends (14 GB at 1M Gaussians);
    otherwise (the means are graph inputs: evaluated in every run) as Gathers."""
    n = x.shape[0]
    if not constant:
        return torch.stack([_product(bilinear_gather(scale[k], x[:, list(PLANE_AXES[k])])
                                     for k in SPACE_PLANES) for scale in hexplane.planes], 1)
    grids = {k: x[:, list(PLANE_AXES[k])].reshape(1, 1, n, 2) for k in SPACE_PLANES}
    per_scale = [_product(F.grid_sample(scale[k], grids[k], mode="bilinear",
                                        padding_mode="border", align_corners=True)
                          for k in SPACE_PLANES) for scale in hexplane.planes]  # (1, C, 1, N)
    return torch.cat(per_scale, 0).reshape(len(per_scale), -1, n).permute(2, 0, 1)


def hexplane_features(hexplane, x: torch.Tensor, tp: torch.Tensor,
                      constant: bool = False) -> torch.Tensor:
    """HexPlane.forward(x, t) (no mipmapping) for x (N, 3) in [-1, 1]^3 and one time tp (1,) in
    [-1, 1] -> (N, S C). `constant`: x depends on initializers only (see `spatial_features`)."""
    n = x.shape[0]
    out = spatial_features(hexplane, x, constant)
    for k in TIME_PLANES:  # axis a paired with t: one stacked table over the scales
        a = PLANE_AXES[k][0]
        tabs, idx, frac, off = [], [], [], 0
        for scale in hexplane.planes:
            table = plane_table(scale[k])
            r = table.shape[1]
            i0, f = lerp_index(x[:, a], r)
            tabs.append(with_differences(time_rows(table, tp)))
            idx.append(i0.to(torch.int64) + off)
            frac.append(f)
            off += r
        a_tab = torch.cat([t[0] for t in tabs], 0)
        d_tab = torch.cat([t[1] for t in tabs], 0)
        out = out * space_time_term(a_tab, d_tab, torch.stack(idx, 1),
                                    torch.stack(frac, 1).unsqueeze(2))
    return out.reshape(n, -1)


def _product(factors):
    out = None
    for f in factors:
        out = f if out is None else out * f
    return out


def mip_levels(hexplane, sigma: torch.Tensor) -> list[torch.Tensor]:
    """l_hat (N,) of every scale (`nehad.field.mipmap.mip_level`, docs/design.md section 8)."""
    from nehad.field.mipmap import mip_level

    return [mip_level(sigma * torch.tensor([(r - 1) * 0.5 for r in res[:3]], dtype=sigma.dtype),
                      l_max) for res, l_max in zip(hexplane.resolutions(), hexplane.mip_levels())]


def mip_spatial_features(hexplane, x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Product of the mipmapped spatial planes per scale, (N, S, C), from the frozen pyramids."""
    frozen = hexplane._export_pyramids
    return torch.stack([_product(frozen[i][k].sample_trilinear(x[:, list(PLANE_AXES[k])], level)
                                 for k in SPACE_PLANES)
                        for i, level in enumerate(mip_levels(hexplane, sigma))], 1)


def mip_hexplane_features(hexplane, x: torch.Tensor, tp: torch.Tensor, sigma: torch.Tensor,
                          spatial: Optional[torch.Tensor] = None) -> torch.Tensor:
    """HexPlane._forward_mipmap(x, t, sigma) for one time tp (1,), from the pyramids frozen by
    `freeze_pyramids_for_export` (docs/design.md section 8) -> (N, S C). Every level of a space-time plane is
    sliced at tp; each point blends its levels lo and lo + 1 (one term when no scale has more
    than one level). `spatial`: `mip_spatial_features` computed beforehand (else it is computed
    here)."""
    n = x.shape[0]
    frozen = hexplane._export_pyramids
    levels = []  # per scale (lo (N,) int64, w (N,) or None)
    for level, l_max in zip(mip_levels(hexplane, sigma), hexplane.mip_levels()):
        if l_max == 0:
            levels.append((torch.zeros_like(level, dtype=torch.int64), None))
        else:
            lo = torch.minimum(level.floor(), torch.full_like(level, float(l_max - 1)))
            levels.append((lo.to(torch.int64), level - lo))
    if spatial is None:
        spatial = mip_spatial_features(hexplane, x, sigma)
    two = any(w is not None for _, w in levels)
    out = spatial
    for k in TIME_PLANES:
        a = PLANE_AXES[k][0]
        tabs, terms, off = [], [[], []], 0
        for i, (lo, w) in enumerate(levels):
            pyr = frozen[i][k]
            c = pyr.table.shape[1]
            starts = []
            for h, wd, o in zip(pyr.heights, pyr.widths, pyr.offsets):
                tabs.append(with_differences(time_rows(pyr.table[o:o + h * wd].reshape(h, wd, c),
                                                       tp)))
                starts.append(off)
                off += wd
            widths = torch.tensor(pyr.widths, dtype=x.dtype)
            starts = torch.tensor(starts, dtype=torch.int64)
            for j in range(2 if two else 1):
                lvl = lo + 1 if (j == 1 and w is not None) else lo
                i0, f = lerp_index(x[:, a], widths[lvl])
                weight = None
                if two:
                    weight = (torch.full_like(f, 1.0 - j) if w is None
                              else (1.0 - w if j == 0 else w))
                terms[j].append((i0.to(torch.int64) + starts[lvl], f, weight))
        a_tab = torch.cat([t[0] for t in tabs], 0)
        d_tab = torch.cat([t[1] for t in tabs], 0)
        value = None
        for term in terms[:2 if two else 1]:
            v = space_time_term(a_tab, d_tab, torch.stack([t[0] for t in term], 1),
                                torch.stack([t[1] for t in term], 1).unsqueeze(2))
            if two:
                v = v * torch.stack([t[2] for t in term], 1).unsqueeze(2)
            value = v if value is None else value + v
        out = out * value
    return out.reshape(n, -1)


# ---------------------------------------------------------------------------- decoders (4.2-4.6)


def _f32(x: torch.Tensor) -> torch.Tensor:
    return x.detach().to(torch.float32).contiguous()


def _block_diag(blocks: list[torch.Tensor]) -> torch.Tensor:
    rows = sum(b.shape[0] for b in blocks)
    cols = sum(b.shape[1] for b in blocks)
    out = blocks[0].new_zeros(rows, cols)
    r = c = 0
    for b in blocks:
        out[r:r + b.shape[0], c:c + b.shape[1]] = b
        r, c = r + b.shape[0], c + b.shape[1]
    return out


def adapter_maps(field, k_sh: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(Q_c, Q_s, bias) in float64 with every adapter output = v_c Q_c + v_s Q_s + bias, columns
    [displacement mu~ - mu (3), ds (3), q (4), (d_opacity (1), d_sh (3 k_sh))]: the displacement
    is dt A_mu v (+ dt^2/2 A_mu' v_c with Verlet, docs/design.md section 4.5-4.6), q includes (1, 0, 0, 0)."""
    cfg, ad = field.cfg, field.adapters
    w = {name: getattr(ad, name).weight.detach().double().t() for name in ("mu", "scale", "rot")}
    b = {name: getattr(ad, name).bias.detach().double() for name in ("mu", "scale", "rot")}
    force = 0.5 * cfg.dt * cfg.dt if cfg.verlet else 0.0
    rest_w = [w["scale"], w["rot"]]
    rest_b = [b["scale"], b["rot"] + ad.identity_quat.double()]
    if ad.opacity is not None:
        rest_w += [ad.opacity.weight.detach().double().t(),
                   ad.sh.weight.detach().double()[:3 * k_sh].t()]
        rest_b += [ad.opacity.bias.detach().double(), ad.sh.bias.detach().double()[:3 * k_sh]]
    q_c = torch.cat([w["mu"] * (cfg.dt + force)] + rest_w, 1)
    q_s = torch.cat([w["mu"] * cfg.dt] + rest_w, 1)
    return q_c, q_s, torch.cat([b["mu"] * cfg.dt] + rest_b)


def quadratic_map(decoder, trunk_last: nn.Linear, q_c: torch.Tensor,
                  q_s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The quadratic terms' share of the adapter outputs (FieldConfig.hnn_quadratic) as one
    Linear of the trunk's input x, (weight, bias) in float64: (S1 h) Q_c + (S2 h) J Q_s = h K with
    h = Wt x + bt, so x (Wt^T K) + bt K."""
    s1 = decoder.quad1.detach().double()
    s2 = decoder.quad2.detach().double()
    k = 0.5 * (s1 + s1.t()) @ q_c + 0.5 * (s2 + s2.t()) @ symplectic_rows(q_s)
    wt, bt = trunk_last.weight.detach().double(), trunk_last.bias.detach().double()
    return (wt.t() @ k).t(), bt @ k


def symplectic_rows(q: torch.Tensor) -> torch.Tensor:
    """J Q for v_s = g M^T = g J (`symplectic`): v_s Q = g (J Q), J Q = (-Q[d:], Q[:d]),
    i.e. (Q^T M)^T (`symplectic_transpose` of Q's columns)."""
    return symplectic_transpose(q.t()).t()


class ClosedFormNet(nn.Module):
    """One scalar net F (docs/design.md section 4.3) with its input gradient contracted with a fixed matrix:
    forward(x) = (grad_h F(h)) @ Q (+ bias) for h = Wt x + bt (the trunk's last Linear, folded
    into F's first layer), in closed form (docs/design.md section 4.4):
        m = act'(z_L) @ (diag(w_out) W_L);  m = (act'(z_l) * m) @ W_l, l = L-1 .. 2;
        out = (act'(z_1) * m) @ (W_1 Q) + bias   (depth 1: act'(z_1) @ (diag(w_out) W_1 Q)).
    For tanh, act'(z) @ M = colsum(M) - (a * a) @ M is a single Gemm."""

    def __init__(self, net, trunk_last: Optional[nn.Linear], q: torch.Tensor,
                 bias: Optional[torch.Tensor]):
        super().__init__()
        self.activation = net.activation
        lin = [(l.weight.detach().double(), l.bias.detach().double()) for l in net.hidden_layers]
        w1, b1 = lin[0]
        if trunk_last is not None:  # z1 = W1 (Wt x + bt) + b1
            wt, bt = trunk_last.weight.detach().double(), trunk_last.bias.detach().double()
            w1, b1 = w1 @ wt, w1 @ bt + b1
        self.depth = len(lin)
        for i, (w, b) in enumerate([(w1, b1)] + lin[1:]):
            self.register_buffer(f"w{i}", _f32(w))
            self.register_buffer(f"b{i}", _f32(b))
        # backward matrices: mats[l] multiplies delta_l; mats[0] is W_1 Q
        mats = [lin[0][0] @ q] + [w for w, _ in lin[1:]]
        mats[-1] = net.out.weight.detach().double().reshape(-1, 1) * mats[-1]
        bias = torch.zeros(q.shape[1], dtype=torch.float64) if bias is None else bias
        for i, m in enumerate(mats):
            b = bias if i == 0 else torch.zeros(m.shape[1], dtype=torch.float64)
            if self.activation == "tanh" and i == self.depth - 1:
                # colsum(M) - (a * a) @ M: the Gemm weight is -M, its bias colsum(M) (+ bias)
                self.register_buffer(f"m{i}", _f32(-m.t()))
                self.register_buffer(f"c{i}", _f32(m.sum(0) + b))
            else:
                self.register_buffer(f"m{i}", _f32(m.t()))
                self.register_buffer(f"c{i}", _f32(b))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        tanh = self.activation == "tanh"
        saved = []
        a = x
        for i in range(self.depth):
            z = F.linear(a, getattr(self, f"w{i}"), getattr(self, f"b{i}"))
            if tanh:
                a = torch.tanh(z)
                saved.append(a)
            else:
                a, da = activation_with_derivative(z, self.activation)
                saved.append(da)
        top = self.depth - 1
        m = saved[top] * saved[top] if tanh else saved[top]
        for i in range(top, -1, -1):
            if i < top:
                m = (1.0 - saved[i] * saved[i] if tanh else saved[i]) * m
            m = F.linear(m, getattr(self, f"m{i}"), getattr(self, f"c{i}"))
        return m


class MLPHeadsGraph(nn.Module):
    """The 4DGS heads (ReLU-Linear(W, W)-ReLU-Linear(W, k) each, `MLPHeads`) on h as two GEMMs:
    the first Linears side by side, the last ones block-diagonal. Columns [dmu (3), ds (3),
    dr (4), (d_opacity (1), d_sh (3 k_sh))]."""

    def __init__(self, heads, k_sh: int):
        super().__init__()
        mods = [heads.pos, heads.scale, heads.rot]
        if heads.opacity is not None:
            mods += [heads.opacity, heads.sh]
        rows = [None] * (len(mods) - 1) + [3 * k_sh if heads.opacity is not None else None]
        firsts = [m[1] for m in mods]
        lasts = [(m[3].weight.detach()[:r], m[3].bias.detach()[:r]) for m, r in zip(mods, rows)]
        self.register_buffer("w_hidden", _f32(torch.cat([f.weight.detach() for f in firsts], 0)))
        self.register_buffer("b_hidden", _f32(torch.cat([f.bias.detach() for f in firsts], 0)))
        self.register_buffer("w_out", _f32(_block_diag([w for w, _ in lasts])))
        self.register_buffer("b_out", _f32(torch.cat([b for _, b in lasts])))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        hidden = torch.relu(F.linear(torch.relu(h), self.w_hidden, self.b_hidden))
        return F.linear(hidden, self.w_out, self.b_out)


# ---------------------------------------------------------------------------- the whole field


class FastDeform(nn.Module):
    """forward(means, log_scales, quats, opacity_logits, sh, mu_eq, t_eq, time [1]) ->
    (means [N,3], scales [N,3], quats [N,4], opacities [N], sh [N,k,3]) as
    `NeHaDModel.gaussians_at(time)` for these canonical Gaussians (docs/design.md section 4, 7), with `sh` the first
    k = (sh_degree + 1)^2 coefficients. `model` should be a `closed_form_copy` (its weights are
    read here, once). `constant_means`: the canonical Gaussians will be initializers (the
    single-file export), not graph inputs (the streaming base graph)."""

    def __init__(self, model, sh_degree: int, constant_means: bool = True):
        super().__init__()
        field = model.field
        self.constant_means = constant_means
        self.drift_window = float(model.gaussians.drift_window)  # GaussianParameters.drift
        self.cfg = cfg = field.cfg
        self.k = (int(sh_degree) + 1) ** 2
        self.hexplane = field.hexplane
        self.register_buffer("aabb", field.aabb.detach().clone())
        self.register_buffer("extent", field.extent.detach().clone())
        self.deform_appearance = cfg.deform_opacity_sh
        if self.deform_appearance and self.k > cfg.sh_coeffs:
            raise ValueError(f"export: sh degree {sh_degree} has {self.k} coefficients, more than "
                             f"field.sh_coeffs = {cfg.sh_coeffs} deformed by the field")
        self.mip_spatial: Optional[torch.Tensor] = None
        if cfg.mipmap and constant_means:
            # the mipmapped spatial planes would leave ~30 (N, C) intermediates per plane in
            # onnxruntime's constant folding (29 GB at 1M Gaussians): computed here, stored
            g = model.gaussians
            with torch.no_grad():
                x, sigma = self._mip_inputs(g.means, g.log_scales, g.quats)
                spatial = mip_spatial_features(self.hexplane, x, sigma).contiguous()
            del self.mip_spatial
            self.register_buffer("mip_spatial", spatial)
        self.mlp = self.hnn = None
        self.register_buffer("quad_w", None)
        self.register_buffer("quad_b", None)
        trunk = list(field.trunk)
        if cfg.decoder == "mlp":
            self.trunk = field.trunk
            self.mlp = MLPHeadsGraph(field.heads, self.k)
        elif isinstance(field.field, HamiltonianDecoder):
            # the trunk's last Linear is folded into F1 and F2 (h is not needed on its own)
            self.trunk = nn.Sequential(*trunk[:-1])
            q_c, q_s, bias = adapter_maps(field, self.k)
            self.hnn = nn.ModuleList([ClosedFormNet(field.field.f1, trunk[-1], q_c, bias),
                                      ClosedFormNet(field.field.f2, trunk[-1],
                                                    symplectic_rows(q_s), None)])
            if field.field.quad1 is not None:  # FieldConfig.hnn_quadratic: S1 h Q_c + S2 h J Q_s
                w, b = quadratic_map(field.field, trunk[-1], q_c, q_s)
                self.register_buffer("quad_w", _f32(w))
                self.register_buffer("quad_b", _f32(b))
        else:  # use_hnn=False ablation: v_c, v_s are direct MLP outputs, adapters precomposed
            self.trunk = field.trunk
            self.direct = field.field
            q_c, q_s, bias = adapter_maps(field, self.k)
            self.register_buffer("q_c", _f32(q_c.t()))
            self.register_buffer("q_s", _f32(q_s.t()))
            self.register_buffer("q_bias", _f32(bias))

    def _mip_inputs(self, means, log_scales, quats):
        """(normalize_aabb(mu), world-axis sigma in its units), as DeformationField.features."""
        from nehad.field.mipmap import world_axis_sigma

        aabb = self.aabb
        sigma = world_axis_sigma(log_scales, quats, self.cfg.norm_eps) * (2.0 / (aabb[1] - aabb[0]))
        return normalize_aabb(means, aabb), sigma.detach()

    def features(self, means, log_scales, quats, tp, rows=None) -> torch.Tensor:
        """`rows`: the Gaussians' rows in the model this was built from (None: all, in order),
        where the stored mipmapped spatial features are looked up."""
        if not self.cfg.mipmap:
            return hexplane_features(self.hexplane, normalize_aabb(means, self.aabb), tp,
                                     self.constant_means)
        x, sigma = self._mip_inputs(means, log_scales, quats)
        spatial = self.mip_spatial
        if spatial is not None and rows is not None:
            spatial = spatial[rows]
        return mip_hexplane_features(self.hexplane, x, tp, sigma, spatial)

    def decode(self, f: torch.Tensor) -> torch.Tensor:
        """The decoder's per-Gaussian outputs (see `adapter_maps` / `MLPHeadsGraph`) as rows,
        (k, N)."""
        x = self.trunk(f) if len(self.trunk) else f
        if self.mlp is not None:
            cols = self.mlp(x)
        elif self.hnn is not None:
            cols = self.hnn[0](x) + self.hnn[1](x)
            if self.quad_w is not None:
                cols = cols + F.linear(x, self.quad_w, self.quad_b)
        else:
            out = self.direct(x)
            cols = F.linear(out.v_c, self.q_c, self.q_bias) + F.linear(out.v_s, self.q_s)
        return cols.t()  # (N, k) -> (k, N): one cheap Transpose (a transB Gemm was slower)

    def forward(self, means, log_scales, quats, opacity_logits, sh, mu_eq, t_eq, time,
                life_rate=None, velocity=None, rows=None):
        # the tail runs on (k, N) rows (see the module doc); `life_rate` [N,1] (None: every
        # Gaussian lives at every time): GaussianParameters.life_factor; `velocity` [N,3]
        # (0 where the life rate is 0): GaussianParameters.drift; `rows`: see `features`
        cfg = self.cfg
        n = means.shape[0]
        t = time.reshape(1, 1).to(means.dtype)
        rows = self.decode(self.features(means, log_scales, quats, (2.0 * t - 1.0).reshape(1),
                                         rows))
        sh = sh[:, :self.k]
        opacity = opacity_logits.reshape(1, n)
        if self.deform_appearance:
            opacity = opacity + rows[10:11]
            sh = sh + rows[11:11 + 3 * self.k].t().reshape(n, self.k, 3)
        opacities = torch.sigmoid(opacity).reshape(n)
        if life_rate is not None:
            lived = life_rate.reshape(n) * (t.reshape(1) - t_eq.reshape(n))
            opacities = opacities * torch.exp(-0.5 * lived * lived)
        mu, log_s, quat = means.t(), log_scales.t(), quats.t()
        drift = None
        if velocity is not None:  # added after the field, as gaussians_at adds it
            dt = t.reshape(1, 1) - t_eq.reshape(1, n)
            if self.drift_window > 0:
                dt = dt.clamp(-self.drift_window, self.drift_window)
            drift = velocity.t() * dt
        if self.mlp is not None:  # 4DGS: mu + dmu, s + ds, r + dr (normalised as gaussians_at)
            new_quats = quat + rows[6:10]
            moved = mu + rows[0:3]
            return ((moved if drift is None else moved + drift).t(), torch.exp(log_s + rows[3:6]).t(),
                    (new_quats / new_quats.norm(dim=0, keepdim=True)).t(), opacities, sh)
        disp, ds, q = rows[0:3], rows[3:6], rows[6:10]
        t_eq = t_eq.reshape(1, n)
        if cfg.bed_position:
            at = mu + disp if cfg.bed_distance == "deformed" else mu
            disp = disp * (1.0 - position_mask(
                at, mu_eq.t(), t, t_eq, sigma_s=cfg.sigma_s_fraction * self.extent.to(means.dtype),
                sigma_t=cfg.sigma_t, beta=cfg.beta, gamma=cfg.gamma, lam=cfg.lam,
                eps=cfg.norm_eps, dim=0, floor=cfg.bed_floor))
        if cfg.bed_scale:
            ds = ds * (1.0 - scale_mask(t, t_eq, sigma_t=cfg.sigma_t, beta=cfg.beta,
                                        gamma=cfg.gamma, floor=cfg.bed_floor))
        dr = clamp_rotation_delta(q, cfg.phi_max, cfg.norm_eps, dim=0).dr if cfg.rigidity else q
        new_quats = safe_normalize(quat_multiply(quat, dr, dim=0), cfg.norm_eps, dim=0)
        moved = mu + disp
        return ((moved if drift is None else moved + drift).t(), torch.exp(log_s + ds).t(),
                (new_quats / new_quats.norm(dim=0, keepdim=True)).t(), opacities, sh)


__all__ = ["ClosedFormNet", "FastDeform", "MLPHeadsGraph", "adapter_maps", "hexplane_features",
           "lerp_index", "mip_hexplane_features", "symplectic_rows", "time_rows"]
