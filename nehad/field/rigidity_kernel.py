"""The rigidity clamp, the quaternion product and the normalisation of step 8 (docs/design.md
section 4.8) as one Numba pass per Gaussian, forward and backward (issue 27;
`FieldConfig.rotation_kernel = "numba"`). `nehad.field.rigidity`'s torch functions are the
reference, the export's form and the GPU path; this computes the same function:

    dw = q_0, g = q_1:3, |g| = sqrt(g.g + eps), phi = 2 atan2(|g|, dw),
    phi' = phi_max tanh(phi / phi_max), dr' = (cos(phi'/2), sin(phi'/2) g / |g|),
    p = r (x) dr',  r' = p / sqrt(p.p + eps)

(the torch form writes atan2 without an Atan2 op for ONNX; here it is math.atan2, equal for
|g| > 0). Where torch ran some sixty small ops over the Gaussians forward and more backward,
each a pass over an (N, 1) or (N, 4) tensor, this is one pass each way. The backward recomputes
the forward from the inputs and applies the chain rule written out:

    dp = dr'_out / s - p (p . dr'_out) / s^3,  s = sqrt(p.p + eps)
    d r = dp (x) conj(dr'),  d dr' = conj(r) (x) dp          (the Hamilton product's transposes)
    d(phi'/2) = -sin(phi'/2) d dr'_0 + cos(phi'/2) (g / |g|) . d dr'_1:3
    dphi' += d(phi'/2) / 2,  dphi += dphi' (1 - tanh^2(phi / phi_max))
    d dw = -2 |g| / (|g|^2 + dw^2) dphi,  d|g| = 2 dw / (|g|^2 + dw^2) dphi
    dg = sin(phi'/2) (du / |g| - g (g . du) / |g|^3) + d|g| g / |g|,  du = d dr'_1:3

Float32 in training, float64 in the tests (tests/test_rigidity_kernel.py: values and gradients
against the torch functions through autograd).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch.autograd.function import once_differentiable


@numba.njit(inline="always")
def _hamilton(aw, ax, ay, az, bw, bx, by, bz):
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


@numba.njit(parallel=True, cache=True)
def _forward(quats, q, phi_max, eps, out, phi, phi_c, trig):
    """out = r', phi, phi' per row; trig = (tanh(phi / phi_max), cos(phi'/2), sin(phi'/2)),
    kept for the backward, which then calls no transcendental function (they are scalar
    library calls here, most of the pass's time)."""
    one = phi_max / phi_max
    half_max = phi_max * (one / (one + one))
    for i in numba.prange(quats.shape[0]):
        gx, gy, gz = q[i, 1], q[i, 2], q[i, 3]
        gn = math.sqrt(gx * gx + gy * gy + gz * gz + eps)
        ph = (one + one) * math.atan2(gn, q[i, 0])
        th = math.tanh(ph / phi_max)
        half = half_max * th
        c, s = math.cos(half), math.sin(half)
        k = s / gn
        pw, px, py, pz = _hamilton(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3],
                                   c, k * gx, k * gy, k * gz)
        inv = one / math.sqrt(pw * pw + px * px + py * py + pz * pz + eps)
        out[i, 0] = pw * inv
        out[i, 1] = px * inv
        out[i, 2] = py * inv
        out[i, 3] = pz * inv
        phi[i, 0] = ph
        phi_c[i, 0] = phi_max * th
        trig[i, 0] = th
        trig[i, 1] = c
        trig[i, 2] = s


@numba.njit(parallel=True, cache=True)
def _backward(quats, q, trig, eps, g_out, g_phi, g_phi_c, g_quats, g_q):
    one = eps / eps
    two = one + one
    half = one / two
    for i in numba.prange(quats.shape[0]):
        th, c, s = trig[i, 0], trig[i, 1], trig[i, 2]
        dw, gx, gy, gz = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        gn = math.sqrt(gx * gx + gy * gy + gz * gz + eps)
        ux, uy, uz = gx / gn, gy / gn, gz / gn
        bw, bx, by, bz = c, s * ux, s * uy, s * uz
        aw, ax, ay, az = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        pw, px, py, pz = _hamilton(aw, ax, ay, az, bw, bx, by, bz)
        inv = one / math.sqrt(pw * pw + px * px + py * py + pz * pz + eps)
        ow, ox, oy, oz = g_out[i, 0], g_out[i, 1], g_out[i, 2], g_out[i, 3]
        dot = (pw * ow + px * ox + py * oy + pz * oz) * inv * inv
        dpw, dpx, dpy, dpz = ((ow - pw * dot) * inv, (ox - px * dot) * inv,
                              (oy - py * dot) * inv, (oz - pz * dot) * inv)
        # p = a (x) b: da = dp (x) conj(b), db = conj(a) (x) dp
        daw, dax, day, daz = _hamilton(dpw, dpx, dpy, dpz, bw, -bx, -by, -bz)
        g_quats[i, 0] = daw
        g_quats[i, 1] = dax
        g_quats[i, 2] = day
        g_quats[i, 3] = daz
        dbw, dbx, dby, dbz = _hamilton(aw, -ax, -ay, -az, dpw, dpx, dpy, dpz)
        # b = (cos(h), sin(h) u), h = phi' / 2
        d_half = -s * dbw + c * (ux * dbx + uy * dby + uz * dbz)
        d_phi_c = g_phi_c[i, 0] + half * d_half
        d_phi = g_phi[i, 0] + d_phi_c * (one - th * th)
        den = gn * gn + dw * dw
        d_gn = two * dw / den * d_phi
        g_q[i, 0] = -two * gn / den * d_phi
        # u = g / |g|: dg = (du - u (u . du)) / |g|, plus d|g| u
        dux, duy, duz = s * dbx, s * dby, s * dbz
        udu = ux * dux + uy * duy + uz * duz
        g_q[i, 1] = (dux - ux * udu) / gn + d_gn * ux
        g_q[i, 2] = (duy - uy * udu) / gn + d_gn * uy
        g_q[i, 3] = (duz - uz * udu) / gn + d_gn * uz


class ClampedRotation(torch.autograd.Function):
    """(r', phi, phi') of canonical unit quaternions r (N, 4) and raw deltas q (N, 4) (module
    docstring), float32 or float64 CPU tensors."""

    @staticmethod
    def forward(ctx, quats, q, phi_max, eps):
        ctx.set_materialize_grads(False)
        a = quats.detach().numpy()
        b = q.detach().numpy()
        out = np.empty((a.shape[0], 4), a.dtype)
        phi = np.empty((a.shape[0], 1), a.dtype)
        phi_c = np.empty((a.shape[0], 1), a.dtype)
        trig = np.empty((a.shape[0], 3), a.dtype)
        _forward(a, b, a.dtype.type(phi_max), a.dtype.type(eps), out, phi, phi_c, trig)
        ctx.save_for_backward(quats, q)
        ctx.trig, ctx.eps = trig, eps
        return torch.from_numpy(out), torch.from_numpy(phi), torch.from_numpy(phi_c)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out, g_phi, g_phi_c):
        quats, q = ctx.saved_tensors
        a, b = quats.detach().numpy(), q.detach().numpy()
        n, dtype = a.shape[0], a.dtype

        def grad(g, cols):
            return np.zeros((n, cols), dtype) if g is None else g.detach().numpy()

        g_quats = np.empty((n, 4), dtype)
        g_q = np.empty((n, 4), dtype)
        _backward(a, b, ctx.trig, dtype.type(ctx.eps), grad(g_out, 4), grad(g_phi, 1),
                  grad(g_phi_c, 1), g_quats, g_q)
        return torch.from_numpy(g_quats), torch.from_numpy(g_q), None, None


def fused_rotation_supported(quats: torch.Tensor, q: torch.Tensor) -> bool:
    """Whether `clamped_rotation` can run: CPU tensors of one float dtype (float32 or float64)."""
    return (quats.device.type == "cpu" and q.device.type == "cpu" and quats.dtype == q.dtype
            and quats.dtype in (torch.float32, torch.float64))


def clamped_rotation(quats: torch.Tensor, q: torch.Tensor, phi_max: float, eps: float):
    """`ClampedRotation` of quats and q: (r' (N, 4), phi (N, 1), phi' (N, 1))."""
    return ClampedRotation.apply(quats, q, float(phi_max), float(eps))


__all__ = ["ClampedRotation", "clamped_rotation", "fused_rotation_supported"]
