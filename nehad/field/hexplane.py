"""Multi-resolution hex-plane encoder (paper Eq. (k-planes) / Alg. 1 "hex-plane feature";
docs/design.md section 4.1; 4DGS `HexPlaneField`).

For u = (x, y, z, t') in [-1, 1]^4 (x, y, z = `normalize_aabb(mu)`, t' = 2t - 1, docs/design.md section 3) and each
scale, the feature is the product over the six planes xy, xz, xt, yz, yt, zt of the bilinear sample
psi(P_k, pi_k(u)); the scales are concatenated. Sampling is `F.grid_sample(mode="bilinear",
align_corners=True, padding_mode="border")` in torch. Under export it is written out as the same
bilinear lookup with Gather (`bilinear_gather`): onnxruntime's CPU GridSample took 30 ms per plane
at 100k points, about 75% of the whole deformation; four row gathers of a (H*W, C) table are
standard ops and much cheaper.

Plane layout follows 4DGS: plane k over the axis pair (a, b) (from `itertools.combinations(
range(4), 2)`) is a Parameter of shape (1, C, res[b], res[a]), so grid_sample's x coordinate is
axis a (width) and its y coordinate is axis b (height); for the space-time planes the height is t.
"""

from __future__ import annotations

import contextlib
import itertools
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from nehad.field._trace import is_capturing

#: Axis pairs of the six planes, in 4DGS order: xy, xz, xt, yz, yt, zt.
PLANE_AXES: tuple[tuple[int, int], ...] = tuple(itertools.combinations(range(4), 2))
PLANE_NAMES: tuple[str, ...] = tuple("xyzt"[a] + "xyzt"[b] for a, b in PLANE_AXES)
SPACE_PLANES: tuple[int, ...] = tuple(k for k, ab in enumerate(PLANE_AXES) if 3 not in ab)
TIME_PLANES: tuple[int, ...] = tuple(k for k, ab in enumerate(PLANE_AXES) if 3 in ab)


def bilinear_gather(plane: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """`F.grid_sample(plane, xy, mode="bilinear", padding_mode="border", align_corners=True)` for
    one plane (1, C, H, W) and points xy (N, 2) in [-1, 1] (x along W), as gathers; (N, C)."""
    _, c, h, w = plane.shape
    px = ((xy[:, 0] + 1.0) * (0.5 * (w - 1))).clamp(0.0, w - 1.0)
    py = ((xy[:, 1] + 1.0) * (0.5 * (h - 1))).clamp(0.0, h - 1.0)
    x0 = px.floor().clamp(max=max(w - 2, 0))
    y0 = py.floor().clamp(max=max(h - 2, 0))
    fx = (px - x0).unsqueeze(1)
    fy = (py - y0).unsqueeze(1)
    table = plane.reshape(c, h * w).transpose(0, 1)  # (H*W, C): one row per texel
    i00 = (y0 * w + x0).to(torch.int64)
    dx = 1 if w > 1 else 0
    dy = w if h > 1 else 0
    top = table[i00] * (1.0 - fx) + table[i00 + dx] * fx
    bottom = table[i00 + dy] * (1.0 - fx) + table[i00 + dy + dx] * fx
    return top * (1.0 - fy) + bottom * fy


def normalize_aabb(x: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """Map points in the box aabb = [[xmin, ymin, zmin], [xmax, ymax, zmax]] to [-1, 1]^3
    (4DGS/K-Planes `normalize_aabb`). Points outside map outside [-1, 1]; the planes' border
    padding then clamps them to the boundary value."""
    return (x - aabb[0]) * (2.0 / (aabb[1] - aabb[0])) - 1.0


def _tv(p: torch.Tensor) -> torch.Tensor:
    """K-Planes total variation of a (1, C, H, W) plane: 2 (mean dH^2 + mean dW^2)."""
    dh = (p[..., 1:, :] - p[..., :-1, :]).square().mean()
    dw = (p[..., :, 1:] - p[..., :, :-1]).square().mean()
    return 2.0 * (dh + dw)


def _second_order(p: torch.Tensor) -> torch.Tensor:
    """4DGS `compute_plane_smoothness`: mean squared second difference along the height axis
    (for a space-time plane the height is t)."""
    d1 = p[..., 1:, :] - p[..., :-1, :]
    return (d1[..., 1:, :] - d1[..., :-1, :]).square().mean()


class HexPlane(nn.Module):
    """Six feature planes per scale; `forward(x, t)` -> (N, out_dim * len(multires)).

    Args:
        out_dim: channels C per plane.
        resolution: base (x, y, z, t) resolution; the spatial entries are multiplied by each
            multires factor, the time entry is not (4DGS).
        multires: spatial upsampling factors, one scale each.
        init_low, init_high: spatial planes ~ U(init_low, init_high).
        time_init: constant initial value of the space-time planes.
    Parameters are `planes.{scale}.{k}` with k indexing PLANE_NAMES.
    """

    def __init__(self, out_dim: int = 32, resolution: Sequence[int] = (64, 64, 64, 25),
                 multires: Sequence[int] = (1, 2), init_low: float = 0.1, init_high: float = 0.5,
                 time_init: float = 1.0):
        super().__init__()
        self.out_dim = int(out_dim)
        self.multires = tuple(int(m) for m in multires)
        self.base_resolution = tuple(int(r) for r in resolution)
        self.planes = nn.ModuleList()
        shapes = []
        for m in self.multires:
            res = [r * m for r in self.base_resolution[:3]] + [self.base_resolution[3]]
            shapes += [(res[b], res[a]) for a, b in PLANE_AXES]
        # every plane a view of one flat buffer, each in channel-last memory (shape (1, C, H, W),
        # memory (H, W, C)): the Numba kernels read and write the planes without reordering or
        # gathering them (nehad.field.hexplane_kernel)
        c = self.out_dim
        flat = torch.empty(sum(c * h * w for h, w in shapes))
        views, lo = [], 0
        for h, w in shapes:
            views.append(flat[lo:lo + c * h * w].view(h, w, c).permute(2, 0, 1)[None])
            lo += c * h * w
        for i, _ in enumerate(self.multires):
            scale = nn.ParameterList()
            for k, (a, b) in enumerate(PLANE_AXES):
                view = views[6 * i + k]
                p = torch.empty(view.shape)  # drawn in (C, H, W) order, as always
                if b == 3:
                    nn.init.constant_(p, time_init)
                else:
                    nn.init.uniform_(p, init_low, init_high)
                view.copy_(p)
                scale.append(nn.Parameter(view))
            self.planes.append(scale)
        #: grid_sample point batches; 0 = automatic (see `_num_batches`), 1 = a single batch.
        self.sample_batches = 0
        #: docs/design.md section 8 mipmapping: the most pyramid levels per scale (0 = as many as the planes allow).
        self.mipmap_levels = 0
        #: "numba": the lookup of float32 CPU points and the planes' regularisers through
        #: nehad.field.hexplane_kernel (not under export or mipmapping); "torch": grid_sample
        #: and autograd
        self.kernel = "torch"
        #: while True (`adding_gradients_in_place`), the Numba lookup's and regularisers'
        #: backwards add the planes' gradients into their `.grad` in place
        self.gradients_in_place = False

    def _numba_ok(self) -> bool:
        """Whether the Numba kernels serve (`kernel` "numba", float32 CPU planes, no capture)."""
        return (self.kernel == "numba" and not is_capturing()
                and all(p.dtype == torch.float32 and p.device.type == "cpu"
                        for p in self.parameters()))

    @contextlib.contextmanager
    def adding_gradients_in_place(self):
        """Lookups and regularisers made inside add their planes' gradients straight into
        the planes' `.grad` at the backward (the lookup where `.grad` is one flat array in the
        planes' layout, as `nehad.optim.TrainingAdam.zero_grad` installs it; the regularisers
        wherever a plane has a `.grad`), instead of returning them for autograd to add: no
        zeroed gradient table, no scaling pass and no additions of 2.4 M values a step
        (docs/performance.md). For a graph that `.backward()` runs through, as a training
        step's; a `torch.autograd.grad` over it would find no plane gradient in its result."""
        before, self.gradients_in_place = self.gradients_in_place, True
        try:
            yield self
        finally:
            self.gradients_in_place = before

    @property
    def feature_dim(self) -> int:
        return self.out_dim * len(self.multires)

    def resolutions(self) -> list[tuple[int, int, int, int]]:
        """(x, y, z, t) resolution of each scale."""
        return [tuple(r * m for r in self.base_resolution[:3]) + (self.base_resolution[3],)
                for m in self.multires]

    def _num_batches(self, x: torch.Tensor) -> int:
        """Point batches for grid_sample. PyTorch's CPU grid_sample backward parallelises over
        the batch dimension only, so with one batch the plane gradients are accumulated on one
        thread; splitting the points into `torch.get_num_threads()` batches (the plane expanded,
        not copied) roughly halves fwd+bwd time on 2 cores. Results are identical up to the
        summation order of the plane gradients. One batch on GPUs, under export/compilation, for
        small N, or when `sample_batches` is set to 1."""
        if self.sample_batches > 0:
            return self.sample_batches
        if x.device.type != "cpu" or is_capturing() or x.shape[0] < 16384:
            return 1
        return max(1, torch.get_num_threads())

    def forward(self, x: torch.Tensor, t: torch.Tensor,
                sigma: torch.Tensor | None = None) -> torch.Tensor:
        """Features of points x (N, 3) in [-1, 1]^3 (already `normalize_aabb`-ed) at times
        t (N, 1) in [-1, 1] (already mapped 2t - 1). Returns (N, out_dim * len(multires)).
        With `sigma` (N, 3), the Gaussians' world-axis standard deviations in the same
        normalised units as x, the planes are sampled through their mip pyramids (docs/design.md section 8,
        `nehad.field.mipmap`)."""
        if sigma is not None:
            return self._forward_mipmap(x, t, sigma)
        n = x.shape[0]
        u = torch.cat([x, t.expand(n, 1).to(x.dtype)], dim=1)  # (N, 4)
        if self._numba_ok() and x.device.type == "cpu" and x.dtype == torch.float32 and n > 0:
            from nehad.field.hexplane_kernel import hexplane_lookup

            return hexplane_lookup(u, [p for scale in self.planes for p in scale], PLANE_AXES,
                                   time_grad=t.requires_grad,
                                   into_grad=self.gradients_in_place)
        b = self._num_batches(x)
        pad = (-n) % b if b > 1 else 0
        if pad:
            u = torch.cat([u, u.new_zeros(pad, 4)], dim=0)
        m = (n + pad) // b if b > 1 else n
        u = u.reshape(b, 1, m, 4)  # point i -> batch i // m, slot i % m
        coords = [u[..., [a, c]] for a, c in PLANE_AXES]  # (b, 1, m, 2) each
        feats = []
        if is_capturing():  # export: gathers instead of GridSample (see the module doc)
            pts = u.reshape(n + pad, 4)
            feats = []
            for scale in self.planes:
                f = None
                for plane, (a, c) in zip(scale, PLANE_AXES):
                    s = bilinear_gather(plane, pts[:, [a, c]])  # (N, C)
                    f = s if f is None else f * s
                feats.append(f)
            out = torch.cat(feats, dim=1)
            return out[:n] if pad > 0 else out
        for scale in self.planes:
            f = None
            for plane, c in zip(scale, coords):
                grid = plane if b == 1 else plane.expand(b, -1, -1, -1)
                s = F.grid_sample(grid, c, mode="bilinear", padding_mode="border",
                                  align_corners=True)  # (b, C, 1, m)
                f = s if f is None else f * s
            feats.append(f)
        out = torch.cat(feats, dim=1).reshape(b, self.feature_dim, m).transpose(1, 2)
        out = out.reshape(b * m, self.feature_dim)
        return out[:n] if pad > 0 else out

    def mip_levels(self) -> list[int]:
        """L_max of each scale (docs/design.md section 8): halvings until a spatial side is 1, capped by
        `mipmap_levels` when that is > 0."""
        from nehad.field.mipmap import auto_levels

        out = []
        for res in self.resolutions():
            n = auto_levels(res[:3])
            out.append(min(n, self.mipmap_levels) if self.mipmap_levels > 0 else n)
        return out

    @torch.no_grad()
    def freeze_pyramids_for_export(self) -> None:
        """Build every plane's mip pyramid table once, as plain tensors that a graph capture
        records as constants (initializers) instead of pooling the planes in every run of the
        exported graph; used only while capturing. Call on an export copy (the tables do not
        follow later changes of the planes)."""
        from nehad.field.mipmap import PlanePyramid, build_pyramid

        self._export_pyramids = [
            [PlanePyramid(build_pyramid(p.detach().clone(), l_max, pool_height=c != 3))
             for p, (_, c) in zip(scale, PLANE_AXES)]
            for scale, l_max in zip(self.planes, self.mip_levels())]

    def _forward_mipmap(self, x: torch.Tensor, t: torch.Tensor,
                        sigma: torch.Tensor) -> torch.Tensor:
        """Scale-aware anisotropic mipmapping (docs/design.md section 8): per scale, the level l_hat of each point
        from its footprint in cells, then a trilinear sample of every plane's pyramid; the
        product over planes and the concatenation over scales as without mipmapping."""
        from nehad.field.mipmap import PlanePyramid, build_pyramid, mip_level

        n = x.shape[0]
        u = torch.cat([x, t.expand(n, 1).to(x.dtype)], dim=1)  # (N, 4)
        sigma = sigma.detach()
        frozen = getattr(self, "_export_pyramids", None) if is_capturing() else None
        feats = []
        for i, (scale, res, l_max) in enumerate(zip(self.planes, self.resolutions(),
                                                    self.mip_levels())):
            cells = torch.tensor([(r - 1) * 0.5 for r in res[:3]], dtype=x.dtype,
                                 device=x.device)
            level = mip_level(sigma * cells, l_max)  # (N,)
            f = None
            for k, (plane, (a, c)) in enumerate(zip(scale, PLANE_AXES)):
                pyr = (frozen[i][k] if frozen is not None
                       else PlanePyramid(build_pyramid(plane, l_max, pool_height=c != 3)))
                s = pyr.sample_trilinear(u[:, [a, c]], level)
                f = s if f is None else f * s
            feats.append(f)
        return torch.cat(feats, dim=1)

    # ------------------------------------------------------------------ regularisers (docs/design.md section 5)
    def plane_smoothness(self, kind: str = "tv") -> torch.Tensor:
        """Smoothness of the spatial planes xy, xz, yz, summed over planes and scales: "tv" =
        K-Planes total variation; "second_order" = the 4DGS code's `_plane_regulation`."""
        fn = _tv if kind == "tv" else _second_order
        if kind == "tv" and self._numba_ok():
            from nehad.field.hexplane_kernel import plane_tv

            fn = plane_tv  # the same function in one Numba pass
        return sum(fn(scale[k]) for scale in self.planes for k in SPACE_PLANES)

    def regularisers(self, kind: str = "tv") -> tuple:
        """(`plane_smoothness(kind)`, *`time_terms()`). With the Numba kernels and "tv", one
        pass per plane inside one autograd Function over all the planes
        (nehad.field.plane_regularisers): the same values and gradients."""
        if kind == "tv" and self._numba_ok():
            from nehad.field.plane_regularisers import plane_regularisers

            return plane_regularisers([p for scale in self.planes for p in scale],
                                      [k in TIME_PLANES for _ in self.planes
                                       for k in range(len(PLANE_AXES))],
                                      into_grad=self.gradients_in_place)
        return (self.plane_smoothness(kind), *self.time_terms())

    def time_terms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(`time_smoothness()`, `time_l1()`); with the Numba kernels both in one pass per
        plane (nehad.field.hexplane_kernel.time_regularisers)."""
        if not self._numba_ok():
            return self.time_smoothness(), self.time_l1()
        from nehad.field.hexplane_kernel import time_regularisers

        pairs = [time_regularisers(scale[k]) for scale in self.planes for k in TIME_PLANES]
        return sum(a for a, _ in pairs), sum(b for _, b in pairs)

    def time_smoothness(self) -> torch.Tensor:
        """Second-order smoothness along t of the space-time planes xt, yt, zt (4DGS
        `_time_regulation`), summed over planes and scales."""
        return sum(_second_order(scale[k]) for scale in self.planes for k in TIME_PLANES)

    def time_l1(self) -> torch.Tensor:
        """Mean |1 - P| of the space-time planes (4DGS `_l1_regulation`: keeps them near the
        static value 1), summed over planes and scales."""
        return sum((1.0 - scale[k]).abs().mean() for scale in self.planes for k in TIME_PLANES)


__all__ = ["HexPlane", "normalize_aabb", "PLANE_AXES", "PLANE_NAMES", "SPACE_PLANES",
           "TIME_PLANES"]
