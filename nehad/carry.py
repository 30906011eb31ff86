"""Objects carried along their tracks (`carve.carry_steps`; docs/training.md, "Objects carried along
their tracks"), a stage after the last training step.

A tracks pass seeds a chain: one Gaussian per frame spacing along an object's path, each trained by
the one or two training views of its time (a MuJoCo rig shows one camera per time). Each member is a
fit to its own view, and between two blocks of training times another camera sees the object drawn
by members that no view of that time trained (docs/results.md, 2026-11-30: the stress occluder's
sphere two and three steps into a held-out gap). Here the object is found again on the final model,
with the chains made transparent (everything they drew is then unexplained), and fitted as one
appearance that every training view of it trains together: K Gaussians whose offsets from the
track's point, shapes, colours and opacities are shared over its whole span.

It is fitted, with everything else held, as the Gaussians it is written out as: K members at every
frame spacing along the track, each living one spacing (`sigma`) and moving with the track's
velocity there, the chains' own format, so that the exported file and the runtime do not change.
Written out (`materialise`), each member's canonical place, scale and rotation are chosen so that
the deformation field, which moves every Gaussian, puts it where the fit had it at its own time.
An object is written in, in place of the chain Gaussians about its path or beside them, only
where the held-out views are closer to their targets with it; its extrapolated ends are judged
apart (`carry_stage`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

#: A member is drawn at the times where its life window is above 1e-3 of its peak (3.7 sigma).
REACH_SIGMAS = 3.7


@dataclass
class CarriedObject:
    """One object: its path (a point and a velocity every frame spacing) and its K shared
    Gaussians (offsets from the path's point, log-scales, quaternions, opacity logits, SH DC)."""

    times: np.ndarray  # (n,)
    points: np.ndarray  # (n, 3)
    velocities: np.ndarray  # (n, 3)
    radius: float  # the object's radius (the blobs' median, in world units)
    offsets: torch.Tensor  # (K, 3)
    log_scales: torch.Tensor  # (K, 3)
    quats: torch.Tensor  # (K, 4)
    opacity_logits: torch.Tensor  # (K, 1)
    sh_dc: torch.Tensor  # (K, 1, 3)
    seen: tuple[float, float] | None = None  # the times its track saw it (first, last blob);
    # the knots past them are extrapolated (None: every knot seen)

    def span(self, sigma: float) -> tuple[float, float]:
        return (float(self.times[0]) - REACH_SIGMAS * sigma,
                float(self.times[-1]) + REACH_SIGMAS * sigma)

    def members_at(self, t: float, sigma: float):
        """(means, scales, unit quats, opacities, sh_dc) of the members drawn at time t: each
        knot's K Gaussians moved with the knot's velocity, their opacity times its life window
        (torch, differentiable in the shared parameters); None when none is drawn."""
        near = np.nonzero(np.abs(self.times - t) <= REACH_SIGMAS * sigma)[0]
        if not len(near):
            return None
        dt = t - self.times[near]
        centres = torch.as_tensor(self.points[near] + self.velocities[near] * dt[:, None],
                                  dtype=torch.float32)
        window = torch.as_tensor(np.exp(-0.5 * (dt / sigma) ** 2), dtype=torch.float32)
        k = self.offsets.shape[0]
        means = (centres[:, None, :] + self.offsets[None]).reshape(-1, 3)
        quats = self.quats / self.quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
        opac = (torch.sigmoid(self.opacity_logits).reshape(1, k) * window[:, None]).reshape(-1)
        rep = len(near)
        return (means, torch.exp(self.log_scales).repeat(rep, 1), quats.repeat(rep, 1), opac,
                self.sh_dc.repeat(rep, 1, 1))


def objects_from_tracks(tracks, cameras, spacing: float, time_range, members: int,
                        rng: np.random.Generator) -> list[CarriedObject]:
    """A CarriedObject per track: knots every `spacing` over the track's span and half a
    `max_gap` past its ends (`nehad.tracks.seeds_along`, within `time_range` widened by as
    much), on the track's smooth path (`Track.smooth_at`: across a held-out gap the stress
    occluder's sphere is then a median 0.06 radii from its true centre at the test times, 0.16
    along the chord); `members` Gaussians uniform in a ball of 0.7 object radii (the blobs'
    median radius at their depth), round, half a radius wide, of the track's colour, opacity
    0.9."""
    from nehad.gaussians import rgb_to_sh_dc
    from nehad.tracks import TrackSettings, seeds_along

    reach = 0.5 * TrackSettings().max_gap
    lo, hi = float(time_range[0]) - reach, float(time_range[1]) + reach
    out = []
    for track in tracks:
        _, _, taus, cols, widths, _ = seeds_along(track, cameras, spacing, lo, hi, 1.0)
        pts, vel = track.smooth_at(taus)
        radius = float(widths[0])
        ball = rng.normal(size=(members, 3))
        ball *= (rng.random(members) ** (1 / 3) / np.linalg.norm(ball, axis=1))[:, None]
        colour = torch.as_tensor(np.clip(cols[0], 0.0, 1.0), dtype=torch.float32)
        leaf = lambda x: x.detach().clone().requires_grad_(True)  # noqa: E731
        out.append(CarriedObject(
            np.asarray(taus, np.float64), np.asarray(pts, np.float64),
            np.asarray(vel, np.float64), radius,
            leaf(torch.as_tensor(0.7 * radius * ball, dtype=torch.float32)),
            leaf(torch.full((members, 3), float(np.log(0.5 * radius)))),
            leaf(torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(members, 1)),
            leaf(torch.full((members, 1), float(np.log(0.9 / 0.1)))),
            leaf(rgb_to_sh_dc(colour).reshape(1, 1, 3).repeat(members, 1, 1)),
            (float(track.times[0]), float(track.times[-1]))))
    return out


#: Adam's learning rates of the shared parameters: 3DGS's for the shapes, opacities and colours;
#: the offsets' in object radii a step (OFFSET_RATE x the object's radius), so that an object
#: of any size, in a scene of any unit, is fitted alike (0.014: 1.6e-3 for the stress
#: occluder's sphere, radius 0.115 as its blobs give it).
LEARNING_RATES = {"log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh_dc": 2.5e-3}
OFFSET_RATE = 0.014


def _with_objects(cloud, objects, t: float, sigma: float):
    """The tensors of a frozen cloud at t (means, scales, quats, opacities, sh) with the objects'
    members drawn at t appended (their SH beyond the DC term zero)."""
    means, scales, quats, opac, sh = cloud
    parts = [(means, scales, quats, opac, sh)]
    for obj in objects:
        drawn = obj.members_at(t, sigma)
        if drawn is None:
            continue
        m, s, q, o, dc = drawn
        rest = torch.zeros((m.shape[0], sh.shape[1] - 1, 3))
        parts.append((m, s, q, o, torch.cat([dc, rest], 1)))
    return [torch.cat([p[i] for p in parts]) for i in range(5)]


def fit_objects(objects, model, views, degree: int, background, sigma: float, steps: int,
                hidden_rows, rng: np.random.Generator) -> list[float]:
    """Fit the objects' shared parameters on the training `views` inside their spans (one view
    a step, L1), the model held, its `hidden_rows` (the chains) transparent; the mean L1 of
    each tenth of the steps."""
    from nehad.splat.rasterize import render_torch

    spans = [obj.span(sigma) for obj in objects]
    picks = [k for k, t in enumerate(views.times) if any(lo <= t <= hi for lo, hi in spans)]
    if not picks or steps <= 0:
        return []
    groups = [{"params": [getattr(o, name) for o in objects], "lr": lr}
              for name, lr in LEARNING_RATES.items()]
    groups += [{"params": [o.offsets], "lr": OFFSET_RATE * o.radius} for o in objects]
    opt = torch.optim.Adam(groups, eps=1e-15)
    hidden = torch.as_tensor(np.asarray(hidden_rows, np.int64))
    clouds, log, tenth = {}, [], []
    from tqdm import tqdm

    for _ in tqdm(range(steps), desc="carried objects", leave=False, disable=None):
        k = picks[int(rng.integers(len(picks)))]
        t = float(views.times[k])
        if k not in clouds:
            with torch.no_grad():
                m, s, q, o, sh = (x.detach() for x in model.gaussians_at(t))
                o = o.clone()
                o[hidden] = 0.0
            clouds[k] = (m, s, q, o, sh)
        res = render_torch(*_with_objects(clouds[k], objects, t, sigma), views.cameras[k],
                           background=background, sh_degree=degree)
        loss = (res.rgb - views.images[k]).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        tenth.append(float(loss.detach()))
        if len(tenth) * 10 >= steps:
            log.append(float(np.mean(tenth)))
            tenth = []
    return log


def materialise(obj: CarriedObject, field, like, sigma: float,
                iterations: int = 30) -> tuple[dict, torch.Tensor]:
    """The object's members as canonical Gaussian parameters (GaussianParameters.NAMES): K per
    knot, living `sigma` around the knot's time and moving with its velocity, each placed so
    that the deformation field takes it to the fitted place, scale and rotation at its own time
    (fixed-point steps: the field's output at a place depends on the place; it is a
    contraction about a moving object, so they converge slowly); `like`: the
    model's GaussianParameters (the shapes of their tensors). Returns (the parameters, (n K,)
    the distance left between each member's place and the fitted one: where the field folds
    space, a place may have no canonical point that it takes there)."""
    from nehad.field.rigidity import quat_multiply

    k, n = obj.offsets.shape[0], len(obj.times)
    with torch.no_grad():
        want_mu = (torch.as_tensor(obj.points, dtype=torch.float32)[:, None]
                   + obj.offsets[None]).reshape(-1, 3)
        want_ls = obj.log_scales.repeat(n, 1)
        want_q = (obj.quats / obj.quats.norm(dim=1, keepdim=True)).repeat(n, 1)
        t_eq = torch.as_tensor(np.repeat(obj.times, k), dtype=torch.float32).reshape(-1, 1)
        mu, ls, q = want_mu.clone(), want_ls.clone(), want_q.clone()
        for i in range(iterations):  # after the first, half steps: no oscillation
            out = field(mu, ls, q, t_eq, mu, t_eq)
            mu += (1.0 if i == 0 else 0.5) * (want_mu - out.means)
            ls += want_ls - out.log_scales
            got = out.quats / out.quats.norm(dim=1, keepdim=True)
            turn = quat_multiply(_conj(q), got)  # q (x) turn = got
            q = quat_multiply(want_q, _conj(turn))
        miss = (field(mu, ls, q, t_eq, mu, t_eq).means - want_mu).norm(dim=1)
        velocity = torch.as_tensor(np.repeat(obj.velocities, k, axis=0), dtype=torch.float32)
        shape = lambda name: (n * k,) + tuple(getattr(like, name).shape[1:])  # noqa: E731
        return {"means": mu, "log_scales": ls, "quats": q,
                "opacity_logits": obj.opacity_logits.detach().repeat(n, 1).reshape(
                    shape("opacity_logits")),
                "sh_dc": obj.sh_dc.detach().repeat(n, 1, 1), "sh_rest": torch.zeros(
                    shape("sh_rest")),
                "mu_eq": mu.clone(), "t_eq": t_eq.reshape(shape("t_eq")),
                "velocity": velocity.reshape(shape("velocity")),
                "life_rate": torch.full(shape("life_rate"), 1.0 / sigma)}, miss


def _conj(q: torch.Tensor) -> torch.Tensor:
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


__all__ = ["CarriedObject", "fit_objects", "materialise", "objects_from_tracks"]
