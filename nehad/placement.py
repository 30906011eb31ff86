"""Canonical Gaussians the deformation field takes to given places (docs/training.md, "Objects
carried along their tracks", step 3).

A Gaussian is drawn where the field takes its canonical mean at the time drawn, so writing one
in at a chosen place x at its own time t means solving field(mu, t) = x for mu. Fixed-point
steps mu += (x - field(mu, t)) / 2 converge where the field is a gentle shift, and stop short
where it folds space: about an object it fits turning fast (the stress thin rod), where its
derivative by mu is far from the identity. Newton steps with that derivative (3x3 a Gaussian,
from autograd) converge there, from x itself, from the fixed point's end and from the canonical
mean of the field's own Gaussian drawn nearest x at t (a point the field does take near x);
each Gaussian keeps its best. Between its times the field moves a written-in Gaussian too: `field_velocity`
is that motion, which a Gaussian carrying its own velocity (its drift) subtracts.
"""

from __future__ import annotations

import torch


def _quat_conj(q: torch.Tensor) -> torch.Tensor:
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def _newton(field, mu, ls, q, t_eq, want_mu, reach: torch.Tensor, steps: int):
    """Damped Newton steps on field(mu, t_eq) = want_mu (each step at most `reach` long)."""
    for _ in range(steps):
        x = mu.detach().clone().requires_grad_(True)
        with torch.enable_grad():
            got = field(x, ls, q, t_eq, x.detach(), t_eq).means
            jac = torch.stack([torch.autograd.grad(got[:, i].sum(), x, retain_graph=i < 2)[0]
                               for i in range(3)], 1)
        step = torch.linalg.lstsq(jac, (want_mu - got.detach())[..., None]).solution[..., 0]
        step = torch.nan_to_num(step)
        length = step.norm(dim=1, keepdim=True).clamp_min(1e-12)
        mu = mu + step * torch.clamp(reach[:, None] / length, max=1.0)
    return mu.detach()


def solve_places(field, want_mu, want_ls, want_q, t_eq, seeds=None, reach=None,
                 iterations: int = 30, newton_steps: int = 20):
    """Canonical (means, log-scales, quats) that the field takes to `want_*` at times `t_eq`
    (N, 1), and (N,) the distance left to want_mu (module docstring). `seeds` (N, 3): other
    starting means for the Newton steps; `reach` (N,): the longest Newton step (None: no
    Newton steps)."""
    from nehad.field.rigidity import quat_multiply

    with torch.no_grad():
        mu, ls, q = want_mu.clone(), want_ls.clone(), want_q.clone()

        def settle(mu, ls, q, moves: bool, count: int):
            for i in range(count):  # after the first, half steps: no oscillation
                out = field(mu, ls, q, t_eq, mu, t_eq)
                if moves:
                    mu = mu + (1.0 if i == 0 else 0.5) * (want_mu - out.means)
                ls = ls + want_ls - out.log_scales
                got = out.quats / out.quats.norm(dim=1, keepdim=True)
                turn = quat_multiply(_quat_conj(q), got)  # q (x) turn = got
                q = quat_multiply(want_q, _quat_conj(turn))
            return mu, ls, q

        def miss(mu, ls, q):
            return (field(mu, ls, q, t_eq, mu, t_eq).means - want_mu).norm(dim=1)

        mu, ls, q = settle(mu, ls, q, True, iterations)
        left = miss(mu, ls, q)
        if reach is None:
            return mu, ls, q, left
        for start in (want_mu, mu, seeds):
            if start is None:
                continue
            tried = _newton(field, start.clone(), ls, q, t_eq, want_mu, reach, newton_steps)
            t_ls, t_q = settle(tried, ls, q, False, 5)[1:]
            t_left = miss(tried, t_ls, t_q)
            better = t_left < left
            mu, ls, q = (torch.where(better[:, None], a, b)
                         for a, b in ((tried, mu), (t_ls, ls), (t_q, q)))
            left = torch.minimum(t_left, left)
        return mu, ls, q, left


def field_velocity(field, mu, ls, q, t_eq, step: float) -> torch.Tensor:
    """(N, 3): how fast the field moves each canonical Gaussian at its time t_eq (a central
    difference over +-`step` of time)."""
    with torch.no_grad():
        ahead = field(mu, ls, q, t_eq + step, mu, t_eq).means
        behind = field(mu, ls, q, t_eq - step, mu, t_eq).means
        return (ahead - behind) / (2.0 * step)


__all__ = ["field_velocity", "solve_places"]
