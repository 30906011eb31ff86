"""Hamiltonian decoder (paper Eq. (field), Alg. 1 "Hamiltonian prediction"; docs/design.md section 4.3-4.4).

Two scalar networks F1, F2: R^W -> R generate
    v_c = grad_h F1(h)                      (conservative: its Jacobian, a Hessian, is symmetric)
    g = grad_h F2(h) = (g_q, g_p),  v_s = g M^T = (g_p, -g_q)   (solenoidal: trace of J = 0)
with M = [[0, I], [-I, 0]] the symplectic matrix, d = W/2, and v = v_c + v_s.

The input gradient is computed either by autograd (docs/design.md section 4.4: `torch.autograd.grad(
F.sum(), h, create_graph=True)`) or in closed form (`scalar_net_input_grad`, used by the ONNX
export; for a tanh MLP grad = W1^T[(1 - a1^2) * W2^T[(1 - a2^2) * w3]]), written with torch ops
or, for training on the CPU, fused with its hand-written backward (`nehad.field.hnn_fused`).
All are the same function.

The activation must be smooth: with ReLU, grad_h F would be piecewise constant in h (the Hessian of
F vanishes almost everywhere), so a loss on v would pass no gradient to h and the planes and the
trunk would learn nothing through v.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from nehad.field._trace import is_capturing
from nehad.field.config import SMOOTH_ACTIVATIONS
from nehad.field.hnn_fused import (fused_field, fused_input_gradients, fused_supported,
                                   symplectic)


# log1p(e) on [0, 1] to 5.4e-4 as e (c1 + e (c2 + e c3)), fitted by weighted least squares
# (docs/performance.md, "Frames in a sequence"); stored negated, as `_softplus` uses them
_LOG1P_GUESS = (-0.9874545668773013, 0.40841264342981454, -0.11464033548246846)


def _softplus(z: torch.Tensor) -> torch.Tensor:
    """softplus(z) = relu(z) + log1p(e), e = exp(-|z|) in (0, 1]. In an exported graph the log1p
    is written with Exp, Mul and Add only: a cubic guess y0 and one Newton step on exp(y) = 1 + e,
    y1 = y0 - 1 + (1 + e) exp(-y0), 3.7e-7 from log1p in float32. onnxruntime's Softplus kernel
    took 9.2 of the 16.4 ms of a 15k-Gaussian deformation and its Log 1.4 ms per (15k, 64)
    array on one thread, its vectorised Exp 0.1 ms (docs/performance.md)."""
    if is_capturing():
        e = torch.exp(-torch.abs(z))
        c1, c2, c3 = _LOG1P_GUESS
        u0 = e * (c1 + e * (c2 + e * c3))  # -y0
        u1 = (u0 + 1.0) - (1.0 + e) * torch.exp(u0)  # -y1
        return torch.relu(z) - u1
    return F.softplus(z)


def activation_with_derivative(z: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(act(z), act'(z)) for the smooth activations of docs/design.md section 4.3, written with plain ops
    (Tanh, Sigmoid, Softplus, Mul, Add) so that they export to ONNX."""
    if name == "tanh":
        a = torch.tanh(z)
        return a, 1.0 - a * a
    if name == "softplus":
        return _softplus(z), torch.sigmoid(z)
    if name == "silu":
        s = torch.sigmoid(z)
        return z * s, s * (1.0 + z * (1.0 - s))
    raise ValueError(f"activation {name!r}: must be one of {SMOOTH_ACTIVATIONS}")


def _activation(z: torch.Tensor, name: str) -> torch.Tensor:
    if name == "tanh":
        return torch.tanh(z)
    if name == "softplus":
        return _softplus(z)
    if name == "silu":
        return F.silu(z)
    raise ValueError(f"activation {name!r}: must be one of {SMOOTH_ACTIVATIONS}")


class ScalarNet(nn.Module):
    """F: R^W -> R, `depth` x [Linear, activation] then Linear(hidden, 1, no bias); -> (N,)."""

    def __init__(self, in_dim: int, hidden: int = 64, depth: int = 2, activation: str = "tanh",
                 init_gain: float = 1.0):
        super().__init__()
        if activation not in SMOOTH_ACTIVATIONS:
            raise ValueError(f"ScalarNet.activation {activation!r}: must be one of "
                             f"{SMOOTH_ACTIVATIONS} (a ReLU gives a piecewise-constant grad_h F)")
        if depth < 1:
            raise ValueError(f"ScalarNet.depth {depth}: must be >= 1")
        self.activation = activation
        dims = [in_dim] + [hidden] * depth
        self.hidden_layers = nn.ModuleList(nn.Linear(i, o) for i, o in zip(dims[:-1], dims[1:]))
        if init_gain != 1.0:
            # Larger initial weights put the activations in their curved range, so grad_h F
            # differs between inputs from the start (FieldConfig.hnn_init_gain).
            with torch.no_grad():
                for lin in self.hidden_layers:
                    lin.weight.mul_(init_gain)
                    lin.bias.mul_(init_gain)
        # No output bias: only grad_h F is used, and a constant would get no gradient.
        self.out = nn.Linear(hidden, 1, bias=False)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        a = h
        for lin in self.hidden_layers:
            a = _activation(lin(a), self.activation)
        return self.out(a).squeeze(-1)


def scalar_net_input_grad(net: ScalarNet, h: torch.Tensor) -> torch.Tensor:
    """Closed-form grad_h net(h) (N, W), no autograd (docs/design.md section 4.4 export form):
    grad = W1^T [act'(z1) * W2^T [act'(z2) * ... W_L^T [act'(z_L) * w_out]]], batched as row
    vectors: delta_L = act'(z_L) * w_out; delta_k = act'(z_k) * (delta_{k+1} W_{k+1});
    grad = delta_1 W_1. Differentiable by ordinary (first-order) autograd."""
    derivs = []
    a = h
    for lin in net.hidden_layers:
        a, da = activation_with_derivative(F.linear(a, lin.weight, lin.bias), net.activation)
        derivs.append(da)
    delta = derivs[-1] * net.out.weight  # (N, H) * (1, H)
    for k in range(len(derivs) - 1, 0, -1):
        delta = derivs[k - 1] * (delta @ net.hidden_layers[k].weight)
    return delta @ net.hidden_layers[0].weight


class FieldOutput(NamedTuple):
    """v = v_c + v_s, each (N, W)."""

    v: torch.Tensor
    v_c: torch.Tensor
    v_s: torch.Tensor


class HamiltonianDecoder(nn.Module):
    """F1, F2 -> (v, v_c, v_s) (docs/design.md section 4.3-4.4).

    `grad_mode` "autograd": `torch.autograd.grad` with `create_graph` when grad mode is on (so the
    loss on v trains F1, F2 and everything upstream); under `torch.no_grad()` autograd is enabled
    locally and the result is detached. Under `torch.inference_mode()` (where autograd cannot be
    re-enabled), while a graph is being captured (ONNX export, jit trace, torch.compile) and in
    "closed_form" mode the explicit gradient is used. "fused": the explicit gradient and its
    hand-written backward as one autograd Function with Numba passes
    (`nehad.field.hnn_fused`; CPU, float32 or float64), in training, under `no_grad` and in
    inference mode alike; while a graph is captured, or on another device or dtype, the
    closed form.
    """

    def __init__(self, width: int = 64, hidden: int = 64, depth: int = 2,
                 activation: str = "tanh", grad_mode: str = "autograd", init_gain: float = 1.0,
                 quadratic: bool = False):
        super().__init__()
        if width % 2:
            raise ValueError(f"HamiltonianDecoder.width {width}: must be even")
        self.f1 = ScalarNet(width, hidden, depth, activation, init_gain)
        self.f2 = ScalarNet(width, hidden, depth, activation, init_gain)
        self.grad_mode = grad_mode
        # FieldConfig.hnn_quadratic: F_k(h) += h^T S_k h / 2 with S_k = (A_k + A_k^T) / 2, so
        # grad_h F_k gains S_k h. Zero at the start: the decoder starts as without it.
        self.quad1 = nn.Parameter(torch.zeros(width, width)) if quadratic else None
        self.quad2 = nn.Parameter(torch.zeros(width, width)) if quadratic else None

    def quadratic_gradients(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(S_1 h, S_2 h), the gradients of the quadratic terms h^T S_k h / 2, each (N, W)."""
        s = 0.5 * torch.cat([self.quad1 + self.quad1.t(), self.quad2 + self.quad2.t()], 1)
        both = h @ s  # one product for the two terms, (N, 2W)
        w = h.shape[-1]
        return both[:, :w], both[:, w:]

    def input_gradients(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(grad_h F1, grad_h F2), each (N, W)."""
        if self._fused(h):
            return fused_input_gradients(self.f1, self.f2, h)
        if (self.grad_mode in ("closed_form", "fused") or torch.is_inference_mode_enabled()
                or is_capturing()):
            return scalar_net_input_grad(self.f1, h), scalar_net_input_grad(self.f2, h)
        if self.grad_mode != "autograd":
            raise ValueError(f"HamiltonianDecoder.grad_mode {self.grad_mode!r}")
        training = torch.is_grad_enabled()
        with torch.enable_grad():
            base = h if (training and h.requires_grad) else h.detach().requires_grad_(True)
            # Two differentiable copies so one backward pass yields both input gradients.
            h1, h2 = base.clone(), base.clone()
            total = self.f1(h1).sum() + self.f2(h2).sum()
            g1, g2 = torch.autograd.grad(total, (h1, h2), create_graph=training)
        if not training:
            g1, g2 = g1.detach(), g2.detach()
        return g1, g2

    def _fused(self, h: torch.Tensor) -> bool:
        """Whether the fused Function computes this call (`grad_mode` "fused", not capturing a
        graph, CPU float32/float64)."""
        return (self.grad_mode == "fused" and not is_capturing()
                and fused_supported(self.f1, self.f2, h, self._kinetic_terms()))

    def _kinetic_terms(self):
        """(A_1, A_2) of the kinetic terms (`quadratic`), or None without them."""
        return None if self.quad1 is None else (self.quad1, self.quad2)

    def fused_features(self, f: torch.Tensor, trunk: nn.Linear, adapters):
        """(None, AdapterOutput, force): the `adapters` (`nehad.field.adapters.Adapters`) and
        their Verlet force of forward(trunk(f)), with the trunk's Linear and the adapters inside
        the fused Function (`nehad.field.hnn_fused.fused_field`'s `trunk` and `heads`), whose
        backward then reaches the Gaussians with a gradient only. The FieldOutput is None: v,
        v_c and v_s are not formed there: the trunk, the nets' first layers, the adapters and the
        force are composed into smaller maps (`hnn_heads._Composed`). None where that Function
        cannot run it (`grad_mode` not "fused", a graph being captured, appearance adapters, a
        trunk without bias, ...): the caller then applies the modules one after the other."""
        if (self.grad_mode != "fused" or is_capturing() or trunk.bias is None
                or adapters.opacity is not None):
            return None
        head = (trunk.weight, trunk.bias)
        tail = (*adapters.stacked(), adapters.mu.weight)
        if not fused_supported(self.f1, self.f2, f, self._kinetic_terms(), head, tail):
            return None
        out, force = fused_field(self.f1, self.f2, f, self._kinetic_terms(), head, tail)
        return None, adapters.split(out), force

    def forward(self, h: torch.Tensor) -> FieldOutput:
        if self._fused(h):
            return FieldOutput(*fused_field(self.f1, self.f2, h, self._kinetic_terms()))
        g1, g2 = self.input_gradients(h)
        if self.quad1 is not None:
            q1, q2 = self.quadratic_gradients(h)
            g1, g2 = g1 + q1, g2 + q2
        v_s = symplectic(g2)
        return FieldOutput(g1 + v_s, g1, v_s)


class DirectFieldDecoder(nn.Module):
    """"HNN off" ablation (FieldConfig.use_hnn = False): two MLPs h -> R^W of the same hidden
    width/depth/activation as F1, F2 output v_c and v_s directly (no gradient structure, so v_c is
    not curl-free and v_s not divergence-free); v = v_c + v_s."""

    def __init__(self, width: int = 64, hidden: int = 64, depth: int = 2,
                 activation: str = "tanh", init_gain: float = 1.0):
        super().__init__()
        if activation not in SMOOTH_ACTIVATIONS:
            raise ValueError(f"DirectFieldDecoder.activation {activation!r}")
        self.activation = activation
        self.g1 = self._mlp(width, hidden, depth)
        self.g2 = self._mlp(width, hidden, depth)
        if init_gain != 1.0:  # the same initial scale as F1, F2's hidden layers
            with torch.no_grad():
                for layers in (self.g1, self.g2):
                    for lin in layers[:-1]:
                        lin.weight.mul_(init_gain)
                        lin.bias.mul_(init_gain)

    @staticmethod
    def _mlp(width: int, hidden: int, depth: int) -> nn.ModuleList:
        dims = [width] + [hidden] * depth + [width]
        return nn.ModuleList(nn.Linear(i, o) for i, o in zip(dims[:-1], dims[1:]))

    def _run(self, layers: nn.ModuleList, h: torch.Tensor) -> torch.Tensor:
        for lin in layers[:-1]:
            h = _activation(lin(h), self.activation)
        return layers[-1](h)

    def forward(self, h: torch.Tensor) -> FieldOutput:
        v_c, v_s = self._run(self.g1, h), self._run(self.g2, h)
        return FieldOutput(v_c + v_s, v_c, v_s)


__all__ = ["ScalarNet", "scalar_net_input_grad", "activation_with_derivative", "symplectic",
           "FieldOutput", "HamiltonianDecoder", "DirectFieldDecoder"]
