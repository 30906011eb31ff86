"""Canonical Gaussians the deformation field takes to given places (docs/training.md, "Objects
carried along their tracks", step 3).

A Gaussian is drawn where the field takes its canonical mean at the time drawn, so writing one
in at a chosen place x at its own time t means solving field(mu, t) = x for mu. Fixed-point
steps mu += (x - field(mu, t)) / 2 converge where the field is a gentle shift, and stop short
where it folds space: about an object it fits turning fast (the stress thin rod), where its
derivative by mu is far from the identity. Newton steps with that derivative (3x3 a Gaussian,
from autograd) converge there, from x itself, from the fixed point's end and from the canonical
mean of the field's own Gaussian drawn nearest x at t (a point the field does take near x),
and, for a carried object's copies, from the same member's place at the neighbouring knots;
each Gaussian keeps its best. Between its times the field moves a written-in Gaussian too:
`field_velocity` is that motion, which a Gaussian carrying its own velocity (its drift)
subtracts.
"""

from __future__ import annotations

import contextlib

import torch


def _quat_conj(q: torch.Tensor) -> torch.Tensor:
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


@contextlib.contextmanager
def _parameters_fixed(field):
    """The field's parameters (a module's; a plain function has none) need no gradient inside:
    the fused decoder's backward then computes the gradient by its input alone, no weight
    gradient (the same input gradient, bit for bit)."""
    params = field.parameters() if isinstance(field, torch.nn.Module) else ()
    held = [p for p in params if p.requires_grad]
    for p in held:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in held:
            p.requires_grad_(True)


def _newton(field, mu, ls, q, t_eq, want_mu, reach: torch.Tensor, steps: int):
    """Damped Newton steps on field(mu, t_eq) = want_mu (each step at most `reach` long)."""
    for _ in range(steps):
        x = mu.detach().clone().requires_grad_(True)
        with torch.enable_grad(), _parameters_fixed(field):
            got = field(x, ls, q, t_eq, x.detach(), t_eq).means
            jac = torch.stack([torch.autograd.grad(got[:, i].sum(), x, retain_graph=i < 2)[0]
                               for i in range(3)], 1)
        step = torch.linalg.lstsq(jac, (want_mu - got.detach())[..., None]).solution[..., 0]
        step = torch.nan_to_num(step)
        length = step.norm(dim=1, keepdim=True).clamp_min(1e-12)
        mu = mu + step * torch.clamp(reach[:, None] / length, max=1.0)
    return mu.detach()


def _settle(field, want, mu, ls, q, t_eq, moves: bool, count: int):
    """Fixed-point steps: on the place (half steps after the first: no oscillation) when
    `moves`, and on the log-scale and rotation, which the field shifts and turns."""
    from nehad.field.rigidity import quat_multiply

    want_mu, want_ls, want_q = want
    for i in range(count):
        out = field(mu, ls, q, t_eq, mu, t_eq)
        if moves:
            mu = mu + (1.0 if i == 0 else 0.5) * (want_mu - out.means)
        ls = ls + want_ls - out.log_scales
        got = out.quats / out.quats.norm(dim=1, keepdim=True)
        turn = quat_multiply(_quat_conj(q), got)  # q (x) turn = got
        q = quat_multiply(want_q, _quat_conj(turn))
    return mu, ls, q


def _miss(field, want_mu, mu, ls, q, t_eq):
    return (field(mu, ls, q, t_eq, mu, t_eq).means - want_mu).norm(dim=1)


def _newton_from(field, start, placed, want, t_eq, reach, steps: int, rows):
    """Newton steps from `start` on `rows`; where they end nearer than `placed` (mu, ls, q,
    left) does, the latter is replaced (in place)."""
    sub = [x[rows] for x in want]
    mu, ls, q, left = (x[rows] for x in placed)
    tried = _newton(field, start[rows], ls, q, t_eq[rows], sub[0], reach[rows], steps)
    t_ls, t_q = _settle(field, sub, tried, ls, q, t_eq[rows], False, 5)[1:]
    t_left = _miss(field, sub[0], tried, t_ls, t_q, t_eq[rows])
    better = t_left < left
    for whole, new, old in zip(placed, (tried, t_ls, t_q, t_left), (mu, ls, q, left)):
        whole[rows] = torch.where(better.reshape((-1,) + (1,) * (new.dim() - 1)), new, old)


def solve_places(field, want_mu, want_ls, want_q, t_eq, seeds=None, reach=None,
                 iterations: int = 30, newton_steps: int = 20, neighbours: int = 0):
    """Canonical (means, log-scales, quats) that the field takes to `want_*` at times `t_eq`
    (N, 1), and (N,) the distance left to want_mu (module docstring). `seeds` (N, 3): other
    starting means for the Newton steps; `reach` (N,): the longest Newton step (None: no
    Newton steps). `neighbours` > 0: rows i and i +- neighbours are one Gaussian at
    neighbouring times (a carried object's member at the next knot), and a row still off by
    over a quarter of its reach starts again from its neighbours' places, three times over,
    so that a place found at one time carries along to the next where the field moves it
    on."""
    want = (want_mu, want_ls, want_q)
    with torch.no_grad():
        mu, ls, q = _settle(field, want, want_mu.clone(), want_ls.clone(), want_q.clone(),
                            t_eq, True, iterations)
        placed = [mu, ls, q, _miss(field, want_mu, mu, ls, q, t_eq)]
        if reach is None:
            return tuple(placed)
        every = torch.arange(len(want_mu))
        for start in (want_mu, placed[0].clone(), seeds):  # the fixed point's end, as it is now
            if start is not None:
                _newton_from(field, start, placed, want, t_eq, reach, newton_steps, every)
        for _ in range(3 if neighbours > 0 else 0):
            for shift in (neighbours, -neighbours):
                rows = torch.nonzero(placed[3] > 0.25 * reach).reshape(-1)
                if len(rows):
                    _newton_from(field, torch.roll(placed[0], shift, 0), placed, want, t_eq,
                                 reach, newton_steps, rows)
        return tuple(placed)


def field_velocity(field, mu, ls, q, t_eq, step: float) -> torch.Tensor:
    """(N, 3): how fast the field moves each canonical Gaussian at its time t_eq (a central
    difference over +-`step` of time)."""
    with torch.no_grad():
        ahead = field(mu, ls, q, t_eq + step, mu, t_eq).means
        behind = field(mu, ls, q, t_eq - step, mu, t_eq).means
        return (ahead - behind) / (2.0 * step)


__all__ = ["field_velocity", "solve_places"]
