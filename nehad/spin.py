"""A tracked object's spin, from the shapes of its blobs (docs/training.md, "Objects that spin").

A rigid object turning at a constant angular velocity w about its tracked point has, at time t,
the spread (covariance) S(t) = R(t) S0 R(t)^T of its body, R(t) = exp([w] (t - t_c)). A view at
time t sees it as a blob whose pixel covariance is, to first order, J S(t) J^T, J the 2x3
derivative of the view's projection at the tracked point. For a fixed w that is linear in the
six numbers of S0, so the best S0 is a linear least-squares fit to the blobs' covariances, and
w is found by a search over its directions and rates (each a least-squares solve) followed by
Gauss-Newton steps, first on the views near t_c and then on ever wider windows of time: a rate
off by dw turns the object dw (t - t_c) away from its place, which a narrow window tolerates
and a wide one measures.

A blob's covariance is symmetric under half a turn, so rates are searched up to a quarter turn
per frame spacing. A round object (a sphere) has a covariance no turn changes: its blobs fit
w = 0 as well as any other w, and `estimate_spin` reports no spin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A spin is reported when it fits the blobs' covariances this much better (relative rms) than
#: no spin does. The shape proposes and the held-out views decide (`nehad.carry_stage` keeps a
#: carried object only where they are closer to their targets with it), so the bar is low: a
#: body whose outline changes little as it turns fits its spin only a little better than none
#: (the stress suite's striped box, 0.6 x 0.4 x 0.6 turning about its tall axis: 0.76 of no
#: spin's misfit, at the right rate and 3 degrees from the right axis; the thin rod 0.07-0.13).
#: Round bodies fit a made-up spin by luck, a little (scene1's spheres: 0.89-0.96).
SPIN_GAIN = 0.8

#: The search stops at its first window when its best turn fits the blobs there no better than
#: this fraction of no spin's fit (the refinement is most of its time). On so few views (5-10)
#: the best of the grid fits noise too: the stress thin rod's two pieces fit 0.13 and 0.07 of
#: no spin's, the checkered sphere 0.58.
LIKELY_GAIN = SPIN_GAIN

#: The search runs on the first window with at least this many blobs (3 numbers each, against
#: the spread's 6 and the spin's 3; on 4-6 blobs the demo's bouncing pieces fitted a turn 0.25
#: to 0.49 of no spin's); a track with fewer blobs reports no spin.
SEARCH_VIEWS = 8

#: The windows of time, either side of t_c, on which w is refined in turn.
WINDOWS = (0.06, 0.15, 0.3, 0.6, float("inf"))


@dataclass(frozen=True)
class Spin:
    """`omega` (3,) rad per unit of time about the tracked point, at time `centre_time` the body
    spread `spread` (3, 3); `fit` and `fit_still` the relative rms misfit of the blobs'
    covariances with it and with none; `round`: a round body's, found from its texture
    (`nehad.texture_spin`; the misfits are its texture's)."""

    omega: np.ndarray
    centre_time: float
    spread: np.ndarray
    fit: float
    fit_still: float
    round: bool = False

    @property
    def spins(self) -> bool:
        return self.fit < SPIN_GAIN * self.fit_still


def rotations(omega_dt: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations exp([v]) of rotation vectors v (..., 3) (Rodrigues: cos a I +
    sin a [k] + (1 - cos a) k k^T, k the unit axis, a the angle), entry by entry: the search
    calls it on thousands of candidates at once (`_misfit`)."""
    angle = np.sqrt((omega_dt ** 2).sum(-1))
    k = omega_dt / np.maximum(angle, 1e-12)[..., None]
    cos, sin = np.cos(angle), np.sin(angle)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    one = 1.0 - cos
    return np.stack([cos + one * x * x, one * x * y - sin * z, one * x * z + sin * y,
                     one * x * y + sin * z, cos + one * y * y, one * y * z - sin * x,
                     one * x * z - sin * y, one * y * z + sin * x, cos + one * z * z],
                    -1).reshape(omega_dt.shape[:-1] + (3, 3))


def projection_jacobians(cameras, points: np.ndarray) -> np.ndarray:
    """(n, 2, 3): the derivative of each camera's pixel (u, v) by the world point, at `points`."""
    out = np.empty((len(points), 2, 3))
    for i, (cam, x) in enumerate(zip(cameras, points)):
        rot = cam.world_to_camera[:3, :3]
        cx, cy, cz = rot @ x + cam.world_to_camera[:3, 3]
        out[i] = np.array([[cam.fx / cz, 0.0, -cam.fx * cx / cz ** 2],
                           [0.0, cam.fy / cz, -cam.fy * cy / cz ** 2]]) @ rot
    return out


_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_FIRST, _SECOND = np.array([a for a, _ in _PAIRS]), np.array([b for _, b in _PAIRS])
_OFF = (_FIRST != _SECOND).astype(np.float64)  # 1 for the off-diagonal pairs


def _misfit(omegas, jac, dts, observed, weights):
    """Relative rms misfit (c,) of each candidate angular velocity (c, 3) and its best spread's
    six numbers (c, 6). The blob covariance J R E_ab R^T J^T of each pair (a, b) of the
    spread's six numbers (E_ab the symmetric unit matrix of the pair), with m = J R and its
    rows m0, m1: (1 + off) m0_a m0_b, (1 + off) m1_a m1_b and m0_a m1_b + m0_b m1_a (half that
    on the diagonal), written out element by element: with these and `_refine`'s candidates
    in one call, `estimate_spin` of the tests' spinning rod 0.37 -> 0.10 s, the same spin
    (2026-12-03; `nehad demo` spent 3.1 s of its 93 in the search before)."""
    rot = rotations(omegas[:, None, :] * dts[None, :, None])  # (c, n, 3, 3)
    m = jac[None] @ rot  # (c, n, 2, 3)
    m0a, m0b = m[..., 0, _FIRST], m[..., 0, _SECOND]  # (c, n, 6)
    m1a, m1b = m[..., 1, _FIRST], m[..., 1, _SECOND]
    design = np.stack([(1.0 + _OFF) * m0a * m0b, (1.0 + _OFF) * m1a * m1b,
                       (0.5 + 0.5 * _OFF) * (m0a * m1b + m0b * m1a)], axis=2)  # (c, n, 3, 6)
    design = design.reshape(len(omegas), -1, 6) * np.repeat(weights, 3)[None, :, None]
    rhs = (observed * weights[:, None]).reshape(-1)
    normal = np.swapaxes(design, -1, -2) @ design + 1e-9 * np.eye(6)
    six = np.linalg.solve(normal, (np.swapaxes(design, -1, -2) @ rhs)[..., None])[..., 0]
    resid = (design @ six[..., None])[..., 0] - rhs
    return np.sqrt((resid ** 2).mean(-1)), six


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / n), np.pi * (1.0 + 5 ** 0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar),
                     np.cos(polar)], 1)


def _search(jac, dts, observed, weights, max_rate: float, window: float, keep: int = 6):
    """The `keep` best distinct candidates of a grid of directions (200, 15 degrees apart) x
    rates (steps that turn the body 0.06 rad more across the window), and no spin."""
    rates = np.arange(0.5, max_rate, 0.06 / window)
    cands = np.concatenate([np.zeros((1, 3)), (sphere_directions(200)[:, None]
                                               * rates[None, :, None]).reshape(-1, 3)])
    errs = np.concatenate([_misfit(cands[i:i + 4000], jac, dts, observed, weights)[0]
                           for i in range(0, len(cands), 4000)])
    picks: list[int] = []
    for i in np.argsort(errs):
        if all(np.linalg.norm(cands[i] - cands[j]) > 2.0 for j in picks):
            picks.append(int(i))
        if len(picks) == keep:
            break
    return [cands[i] for i in picks]


def _refine(omegas, jac, dts, observed, weights, iterations: int = 15):
    """Damped Gauss-Newton steps on the misfit (finite differences, diagonal curvature) of each
    candidate of `omegas` (k, 3), all of them in each call of `_misfit` (one candidate a call
    spent most of the search in numpy's call overhead). Each candidate's steps are its own,
    as when refined alone: (k, 3), (k,)."""
    omegas = np.array(omegas, np.float64).reshape(-1, 3)
    k, eye = len(omegas), np.eye(3)
    err = _misfit(omegas, jac, dts, observed, weights)[0]
    damping = np.full(k, 1e-3)
    for _ in range(iterations):
        h = 1e-4 * np.maximum(1.0, np.linalg.norm(omegas, axis=1))[:, None]  # (k, 1)
        probes = np.concatenate([omegas[:, None], omegas[:, None] + h[:, :, None] * eye,
                                 omegas[:, None] - h[:, :, None] * eye], axis=1)  # (k, 7, 3)
        e = _misfit(probes.reshape(-1, 3), jac, dts, observed, weights)[0].reshape(k, 7)
        grad = (e[:, 1:4] - e[:, 4:7]) / (2 * h)
        curv = np.abs(e[:, 1:4] - 2 * e[:, :1] + e[:, 4:7]) / h ** 2
        trial = omegas - grad / (curv + damping[:, None])
        e_trial = _misfit(trial, jac, dts, observed, weights)[0]
        better = e_trial < err
        omegas = np.where(better[:, None], trial, omegas)
        err = np.where(better, e_trial, err)
        damping = np.where(better, damping * 0.5, damping * 10.0)
    return omegas, err


def estimate_spin(blobs, cameras, points: np.ndarray, spacing: float) -> Spin:
    """The Spin of a track whose `blobs` (with shapes) were seen by `cameras` (indexed by the
    blobs' views) at `points` (the track's point at each blob's time); `spacing`: the frame
    spacing, which bounds the rates that can be told apart (module docstring)."""
    times = np.array([b.time for b in blobs], np.float64)
    centre = 0.5 * (times.min() + times.max())
    jac = projection_jacobians([cameras[b.view] for b in blobs], np.asarray(points, np.float64))
    observed = np.array([[b.shape[0, 0], b.shape[1, 1], b.shape[0, 1]] for b in blobs])
    weights = 1.0 / np.array([np.trace(b.shape) for b in blobs])
    dts = times - centre
    best = None
    for window in WINDOWS:
        inside = np.abs(dts) <= window
        if inside.sum() < (4 if best is not None else SEARCH_VIEWS):
            continue
        args = (jac[inside], dts[inside], observed[inside], weights[inside])
        if best is None:
            best = _search(*args, max_rate=0.5 * np.pi / spacing, window=min(window, 1.0))
            first = _misfit(np.stack([best[0], np.zeros(3)]), *args)[0]
            if first[0] >= LIKELY_GAIN * first[1]:  # no turn stands out: a still body
                best = [np.zeros(3)]
                break
        refined, errs = _refine(np.stack(best), *args)
        best = list(refined[np.argsort(errs, kind="stable")])
    args = (jac, dts, observed, weights)
    omega = best[0] if best else np.zeros(3)
    fit, six = _misfit(omega[None], *args)
    still = _misfit(np.zeros((1, 3)), *args)[0][0]
    spread = np.zeros((3, 3))
    for value, (a, b) in zip(six[0], _PAIRS):
        spread[a, b] = spread[b, a] = value
    return Spin(omega, float(centre), spread, float(fit[0]), float(still))


__all__ = ["LIKELY_GAIN", "SEARCH_VIEWS", "SPIN_GAIN", "Spin", "estimate_spin",
           "projection_jacobians", "rotations", "sphere_directions"]
