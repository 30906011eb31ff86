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
apart (`carry_stage`). An object that spins (`nehad.spin_tracks`) turns with its spin: each
copy is the body turned as it is at its knot's time, moving with w x its offset besides its
path's velocity (docs/training.md, "Objects that spin")."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np
import torch

#: A member is drawn at the times where its life window is above 1e-3 of its peak (3.7 sigma).
REACH_SIGMAS = 3.7

#: A round object's members start uniform in a ball of MEMBER_SPREAD object radii, each
#: MEMBER_WIDTH radii wide (a standard deviation), about the object's size together. Started at
#: 0.7 and 0.5, the fit shrank the object by drawing every member to its centre (on the fast ball
#: variant 0.62 -> 0.03 radii apart, one flat colour where the ball is shaded); 0.2 wide kept them
#: apart but cost `nehad demo`'s bouncing ball 1.7 dB in a quarter, 0.3 wide 1.0 (docs/results.md,
#: 2026-12-01).
MEMBER_SPREAD = 0.6
MEMBER_WIDTH = 0.3


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
    omega: torch.Tensor | None = None  # (3,) its spin (`nehad.spin`), rad per unit of time
    # about the path's point, refined by the fit; the offsets and rotations are the body's at
    # `spin_time` (None: no spin)
    spin_time: float = 0.0
    path_fix: torch.Tensor | None = None  # (c, 3) a correction of its path at `fix_times`,
    # fitted, linear between them (its blobs' centroids are off its centre where an occluder
    # hides part of it, and a spinning object's where its outline and shading move about the
    # point it turns about; None: no correction)
    fix_times: np.ndarray | None = None  # (c,)
    seen_times: np.ndarray | None = None  # its track's blobs' times (`refit_unseen`)
    round_spin: bool = False  # a round body whose spin its texture showed (`nehad.texture_spin`)

    def turns(self, times: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """The body's rotation at `times` (the knots' times) since `spin_time`, as (m, 3, 3)
        matrices and (m, 4) unit quaternions (w, x, y, z), differentiable in `omega`; the
        identity without a spin."""
        from nehad.splat.projection import quat_to_rotmat

        m = len(times)
        if self.omega is None:
            quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(m, 1)
            return torch.eye(3).repeat(m, 1, 1), quat
        dt = torch.as_tensor(np.asarray(times, np.float64) - self.spin_time, dtype=torch.float32)
        vec = dt[:, None] * self.omega[None]
        angle = torch.sqrt((vec * vec).sum(1, keepdim=True) + 1e-20)
        quat = torch.cat([torch.cos(0.5 * angle), torch.sin(0.5 * angle) * vec / angle], 1)
        return quat_to_rotmat(quat), quat

    def placed(self, knots: np.ndarray):
        """Per knot of `knots` (indices) its K members' (offsets from the path's point, turned,
        (m, K, 3); velocities from the spin (m, K, 3); quaternions turned (m, K, 4)): the body
        as it is at each knot's time, each member moving with the spin's velocity there
        (w x its offset from the point turned about, and the path correction's rate); the
        path's correction (`path_fix`) included."""
        from nehad.field.rigidity import quat_multiply

        mats, quats = self.turns(self.times[knots])
        turned_offs = torch.einsum("mij,kj->mki", mats, self.offsets)
        swirl = (torch.zeros_like(turned_offs) if self.omega is None else
                 torch.cross(self.omega.expand_as(turned_offs), turned_offs, dim=-1))
        offs = turned_offs
        if self.path_fix is not None:
            at, rate = _linear_weights(self.fix_times, self.times[knots])
            offs = offs + (at @ self.path_fix)[:, None, :]
            swirl = swirl + (rate @ self.path_fix)[:, None, :]
        unit = self.quats / self.quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
        turned = quat_multiply(quats[:, None, :].expand(-1, unit.shape[0], -1),
                               unit[None].expand(len(knots), -1, -1))
        return offs, swirl, turned

    def span(self, sigma: float) -> tuple[float, float]:
        return (float(self.times[0]) - REACH_SIGMAS * sigma,
                float(self.times[-1]) + REACH_SIGMAS * sigma)

    def fitted_span(self, sigma: float) -> tuple[float, float]:
        """The times whose training views fit it: those its track saw, widened by one life
        `sigma`. Past them the object may be gone (landed, hidden, out of the picture), and views
        there would fit its shared opacity down to hide its extrapolated copies: the fast ball
        variant's ball, fitted on its whole span, scored 5-7 dB lower on its own pixels than
        before the fit (docs/results.md, 2026-12-01). Whether those copies are drawn is the
        held-out views' choice (`nehad.carry_stage`)."""
        if self.seen is None:
            return self.span(sigma)
        return self.seen[0] - sigma, self.seen[1] + sigma

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
        offs, swirl, quats = self.placed(near)
        step = torch.as_tensor(dt, dtype=torch.float32)[:, None, None]
        means = (centres[:, None, :] + offs + swirl * step).reshape(-1, 3)
        opac = (torch.sigmoid(self.opacity_logits).reshape(1, k) * window[:, None]).reshape(-1)
        rep = len(near)
        return (means, torch.exp(self.log_scales).repeat(rep, 1), quats.reshape(-1, 4), opac,
                self.sh_dc.repeat(rep, 1, 1))


#: A round spinning body's members start on a sphere this fraction of its radius about its
#: centre (what shows its texture is its surface), each as wide as SURFACE_WIDTH of the
#: spacing of K points spread evenly over its surface.
SURFACE = 0.8
SURFACE_WIDTH = 0.5


def _members_start(spin, radius: float, normal: np.ndarray, rng: np.random.Generator):
    """(offsets (K, 3), width, the body's largest variance) of a carried object's members at
    the start of its fit (`objects_from_tracks`), from K `normal` draws: without a spin uniform
    in a ball of MEMBER_SPREAD `radius`; a round body's on its surface (`_on_surface`; its
    spread is its blobs', nehad.spin_tracks.ball_radius); another spinning body's a normal of
    its spread, as thin as its thinnest spread."""
    if spin is None:
        k = len(normal)
        ball = normal * (MEMBER_SPREAD * radius * rng.random(k) ** (1 / 3)
                         / np.linalg.norm(normal, axis=1))[:, None]
        return ball, MEMBER_WIDTH * radius, 0.0
    if spin.round:
        return (*_on_surface(normal, 2.0 * float(np.sqrt(spin.spread[0, 0]))),
                float(spin.spread[0, 0]))
    values, axes = np.linalg.eigh(spin.spread)
    values = np.clip(values, (0.05 * radius) ** 2, None)
    return (normal @ (axes * np.sqrt(values)).T,
            min(0.5 * radius, float(np.sqrt(values[0]))), float(values[-1]))


def _on_surface(normal: np.ndarray, radius: float) -> tuple[np.ndarray, float]:
    """(members' offsets (K, 3) on the sphere of SURFACE `radius`, in the directions of the
    `normal` draws (K, 3); their width)."""
    k = len(normal)
    dirs = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return SURFACE * radius * dirs, SURFACE_WIDTH * radius * float(np.sqrt(4.0 * np.pi / k))


def _linear_weights(knots: np.ndarray, times: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(m, c) weights of the values at `knots` (c,) that give their piecewise-linear
    interpolation at `times` (m,) (constant past the ends), and (m, c) those of its slope."""
    c = len(knots)
    at, rate = np.zeros((len(times), c)), np.zeros((len(times), c))
    if c == 1:
        at[:, 0] = 1.0
    else:
        i = np.clip(np.searchsorted(knots, times) - 1, 0, c - 2)
        gap = knots[i + 1] - knots[i]
        u = np.clip((times - knots[i]) / gap, 0.0, 1.0)
        rows = np.arange(len(times))
        at[rows, i], at[rows, i + 1] = 1.0 - u, u
        inside = (times >= knots[0]) & (times <= knots[-1])
        step = inside / gap
        rate[rows, i], rate[rows, i + 1] = -step, step
    return (torch.as_tensor(at, dtype=torch.float32), torch.as_tensor(rate, dtype=torch.float32))


def objects_from_tracks(tracks, cameras, spacing: float, time_range, members: int,
                        rng: np.random.Generator, spins=None,
                        fix_every: float = 0.0) -> list[CarriedObject]:
    """A CarriedObject per track: knots every `spacing` over the track's span and half a
    `max_gap` past its ends (`nehad.tracks.seeds_along`, within `time_range` widened by as
    much), on the track's smooth path (`Track.smooth_at`: across a held-out gap the stress
    occluder's sphere is then a median 0.06 radii from its true centre at the test times, 0.16
    along the chord); `members` Gaussians uniform in a ball of MEMBER_SPREAD object radii (the
    blobs' median radius at their depth), round, MEMBER_WIDTH radii wide, of the track's
    colour, opacity 0.9. With `spins` (a `nehad.spin.Spin` per track), each object turns with
    its track's spin, on its smoothed path (`nehad.spin_tracks.smooth_path`); its members start
    spread as its body is (a normal of the body's spread at the spin's time) and as wide as its
    thinnest spread (and at most half a radius), its radius the larger of its blobs' and the
    body's (sqrt(3) times its longest standard deviation: a uniform rod's half length). Every
    object's path gets a correction to fit (`path_fix`) at most `fix_every` apart in time (0:
    none)."""
    from nehad.gaussians import rgb_to_sh_dc
    from nehad.tracks import TrackSettings, seeds_along

    reach = 0.5 * TrackSettings().max_gap
    lo, hi = float(time_range[0]) - reach, float(time_range[1]) + reach
    out = []
    for i, track in enumerate(tracks):
        _, _, taus, cols, widths, _ = seeds_along(track, cameras, spacing, lo, hi, 1.0)
        spin = spins[i] if spins is not None else None
        if spin is None or spin.round:
            pts, vel = track.smooth_at(taus)
        else:
            from nehad.spin_tracks import smooth_path

            pts, vel = smooth_path(track, taus)
        radius, (ball, width, largest) = float(widths[0]), _members_start(
            spin, float(widths[0]), rng.normal(size=(members, 3)), rng)
        colour = torch.as_tensor(np.clip(cols[0], 0.0, 1.0), dtype=torch.float32)
        leaf = lambda x: x.detach().clone().requires_grad_(True)  # noqa: E731
        out.append(CarriedObject(
            np.asarray(taus, np.float64), np.asarray(pts, np.float64),
            np.asarray(vel, np.float64),
            radius if spin is None else max(radius, float(np.sqrt(3 * largest))),
            leaf(torch.as_tensor(ball, dtype=torch.float32)),
            leaf(torch.full((members, 3), float(np.log(width)))),
            leaf(torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(members, 1)),
            leaf(torch.full((members, 1), float(np.log(0.9 / 0.1)))),
            leaf(rgb_to_sh_dc(colour).reshape(1, 1, 3).repeat(members, 1, 1)),
            (float(track.times[0]), float(track.times[-1])),
            None if spin is None else leaf(torch.as_tensor(spin.omega, dtype=torch.float32)),
            0.0 if spin is None else spin.centre_time,
            *((None, None) if fix_every <= 0 else
              _path_fix(np.array([b.time for b in track.blobs]), fix_every)),
            np.sort([b.time for b in track.blobs]), spin is not None and spin.round))
    return out


#: After the fit, the knots an object's track did not see are re-placed from its corrected path
#: (`refit_unseen`): past each end along a quadratic fitted over the times of its END_BLOBS blobs
#: nearest the end (the track's own end fit takes as many); across a gap along the track's own
#: path or a polynomial of each of GAP_DEGREES fitted over GAP_BLOBS blobs on either side (the
#: knots within half a knot spacing of them), whichever the held-out views in the gap prefer. A
#: gap is two of its blobs more than GAP_STEPS of its median step apart (a held-out block of
#: times). No one choice serves every gap: on two occluder variants, the cubic over 5 blobs a
#: side was the closest to the truth across 4 of 10 gaps, over 7 blobs across 3, the two level
#: across 1, the track's own path across 2; across a fast ball's block in mid-flight, with one
#: blob after it, the quadratics were the closest (docs/training.md, "Objects carried along
#: their tracks", step 6).
END_BLOBS = 7
#: The other ways past an end that the held-out views beyond it may prefer (`refit_unseen`),
#: (degree, blobs): a quadratic over twice as many blobs and a straight line over END_BLOBS,
#: steadier where the blobs nearest the end are slivers of an object an occluder hides.
END_OTHERS = ((2, 2 * END_BLOBS), (1, END_BLOBS))
GAP_BLOBS = (5, 7)
GAP_DEGREES = (3, 2)
GAP_STEPS = 2.5


def refit_unseen(obj: CarriedObject, choose=None) -> None:
    """Re-place the object's knots that its track did not see, past its ends and across its
    gaps, from its path as the fit corrected it (`path_fix`): a polynomial motion fitted, by
    least squares, to the corrected points at its knots about them (END_BLOBS, GAP_BLOBS), its
    place and velocity there taken. Across a gap `choose(obj, (a, b), options)` says which of
    the options (the track's own path first, then a polynomial per GAP_DEGREES and GAP_BLOBS,
    the cubics first; each an object with those knots) to take; without it, or where it
    returns None, the first cubic. Past each end it says the same of the quadratic over
    END_BLOBS, the END_OTHERS and the track's own path, the span open on the far side; without
    it, or with no held-out view there, the quadratic. Without a correction nothing changes.

    The track's own path there (`Track.smooth_at`) runs on along a quadratic through its end
    blobs and crosses a gap along a cubic through the two samples at its edges, and where an
    occluder hides part of the object about them their centroids are off its centre. On two
    occluder variants whose spheres pass behind a wall's end or a pillar, the track's path was
    0.4-1.4 radii off at the test times past the last training view and up to 0.8 across a
    held-out block; from the corrected path 0.1-0.45 past the end, and 0.24-0.33 across that
    block (docs/training.md, "Objects carried along their tracks", step 6).

    Not for a spinning object: its path (`nehad.spin_tracks.smooth_path`) is already a fit over
    a wide window, run on along a straight line, since its blobs' centroids wander about its
    centre as it turns; a quadratic over its end took the stress thin rod's copies off their
    place past its last training view (its last quarter +11.1 -> +6.7 dB over blank)."""
    if (obj.path_fix is None or obj.omega is not None or obj.seen_times is None
            or len(obj.seen_times) < 3):
        return
    with torch.no_grad():
        at, rate = _linear_weights(obj.fix_times, obj.times)
        fix, fix_rate = (at @ obj.path_fix).numpy(), (rate @ obj.path_fix).numpy()
    times, seen, eps = obj.times, np.unique(obj.seen_times), 1e-9
    inside = lambda lo, hi: (times >= lo - eps) & (times <= hi + eps)  # noqa: E731
    own = replace(obj, points=obj.points.copy(), velocities=obj.velocities.copy())
    for where, origin, span, blobs in (
            (times < seen[0] - eps, seen[0], (-np.inf, seen[0]), lambda n: seen[:n]),
            (times > seen[-1] + eps, seen[-1], (seen[-1], np.inf), lambda n: seen[-n:])):
        options = []
        for degree, n in ((2, END_BLOBS),) + END_OTHERS:
            window = inside(blobs(n).min(), blobs(n).max())
            points, velocities = _refit(obj, fix, fix_rate, window, where, origin, degree)
            options.append(replace(obj, points=points, velocities=velocities))
        options.append(own)
        pick = choose(obj, span, options) if choose is not None and where.any() else None
        chosen = options[0 if pick is None else pick]
        obj.points, obj.velocities = obj.points.copy(), obj.velocities.copy()
        obj.points[where], obj.velocities[where] = chosen.points[where], chosen.velocities[where]
    steps = np.diff(seen)
    pad = 0.5 * float(np.median(np.diff(times))) if len(times) > 1 else 0.0
    for i in np.nonzero(steps > GAP_STEPS * np.median(steps))[0]:
        a, b = seen[i], seen[i + 1]
        where, options = (times > a + eps) & (times < b - eps), [obj]
        for degree, n in itertools.product(GAP_DEGREES, GAP_BLOBS):
            window = (inside(seen[max(i + 1 - n, 0)] - pad, a + pad)
                      | inside(b - pad, seen[min(i + n, len(seen) - 1)] + pad))
            points, velocities = _refit(obj, fix, fix_rate, window, where, 0.5 * (a + b), degree)
            options.append(replace(obj, points=points, velocities=velocities))
        pick = choose(obj, (a, b), options) if choose is not None else None
        chosen = options[1 if pick is None else pick]
        obj.points, obj.velocities = chosen.points, chosen.velocities


def _refit(obj: CarriedObject, fix, fix_rate, window, where, origin: float, degree: int):
    """The object's (points, velocities) with its knots `where` on a polynomial motion of
    `degree` fitted to its corrected points (`fix` added) at its knots `window`, less the
    correction (`fix`, `fix_rate`) there; as they were where the window is too small."""
    points, velocities = obj.points.copy(), obj.velocities.copy()
    if not where.any() or window.sum() <= degree:
        return points, velocities
    times, poly = obj.times, np.polynomial.polynomial
    scale = max(float(np.abs(times[window] - origin).max()), 1e-9)  # time in [-1, 1]
    coef = poly.polyfit((times[window] - origin) / scale, points[window] + fix[window], degree)
    u = (times[where] - origin) / scale
    points[where] = poly.polyval(u, coef).T - fix[where]
    velocities[where] = poly.polyval(u, poly.polyder(coef)).T / scale - fix_rate[where]
    return points, velocities


def _path_fix(seen: np.ndarray, every: float):
    """A zero path correction (`CarriedObject.path_fix`) and its times: times its track saw
    (`seen`, its blobs'), each the first at least `every` after the one before, and the last.
    None falls inside a gap of the track (a held-out block of times): no view there would fit
    it, and across such a gap the stress thin rod's correction drifted 0.05 off its fixed
    centre; past the times it holds its ends' values."""
    seen = np.unique(np.asarray(seen, np.float64))
    times = [float(seen[0])]
    for t in seen[1:]:
        if t >= times[-1] + every - 1e-9:
            times.append(float(t))
    if seen[-1] > times[-1]:
        times.append(float(seen[-1]))
    return torch.zeros((len(times), 3), requires_grad=True), np.array(times)


#: Adam's learning rates of the shared parameters: 3DGS's for the shapes, opacities and colours;
#: the offsets' in object radii a step (OFFSET_RATE x the object's radius), so that an object
#: of any size, in a scene of any unit, is fitted alike (0.014: 1.6e-3 for the stress
#: occluder's sphere, radius 0.115 as its blobs give it).
LEARNING_RATES = {"log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh_dc": 2.5e-3}
OFFSET_RATE = 0.014
#: The places' learning rates (offsets, shift, spin) fall this much over the fit, geometrically
#: (3DGS lowers its means' 100-fold): at a constant rate the stress thin rod's members kept
#: jittering by a sixth of its thickness, and it scored +6.8 dB over blank on its training
#: views against +10.5 with the fall (docs/training.md, "Objects that spin").
PLACE_DECAY = 0.1
#: A spin's rate, in radians a step over its object's span (a rate off by dw turns the body
#: dw x span/2 from its place at the span's ends).
SPIN_RATE = 0.004


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
    """Fit the objects' shared parameters on the training `views` inside their fitted spans
    (`CarriedObject.fitted_span`; one view a step, L1), the model held, its `hidden_rows` (the
    chains) transparent; the mean L1 of each tenth of the steps."""
    from nehad.splat.rasterize import render_torch

    spans = [obj.fitted_span(sigma) for obj in objects]
    picks = [k for k, t in enumerate(views.times) if any(lo <= t <= hi for lo, hi in spans)]
    if not picks or steps <= 0:
        return []
    groups = [{"params": [getattr(o, name) for o in objects], "lr": lr}
              for name, lr in LEARNING_RATES.items()]
    still = len(groups)  # the places' groups follow (their rates fall)
    groups += [{"params": [o.offsets], "lr": OFFSET_RATE * o.radius} for o in objects]
    groups += [{"params": [o.path_fix], "lr": OFFSET_RATE * o.radius} for o in objects
               if o.path_fix is not None]
    groups += [{"params": [o.omega], "lr": SPIN_RATE / max(hi - lo, 1e-3)}
               for o, (lo, hi) in zip(objects, spans) if o.omega is not None]
    opt = torch.optim.Adam(groups, eps=1e-15)
    hidden = torch.as_tensor(np.asarray(hidden_rows, np.int64))
    clouds, log, tenth = {}, [], []
    from tqdm import tqdm

    decay = PLACE_DECAY ** (1.0 / steps)
    moving_groups = opt.param_groups[still:]
    for _ in tqdm(range(steps), desc="carried objects", leave=False, disable=None):
        for group in moving_groups:
            group["lr"] *= decay
        k = picks[int(rng.integers(len(picks)))]
        t = float(views.times[k])
        if k not in clouds:
            clouds[k] = _held_cloud(model, t, hidden)
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


def _held_cloud(model, t: float, hidden: torch.Tensor):
    """The model's Gaussians at t (means, scales, quats, opacities, sh), detached, its `hidden`
    rows transparent."""
    with torch.no_grad():
        m, s, q, o, sh = (x.detach() for x in model.gaussians_at(t))
        o = o.clone()
        o[hidden] = 0.0
    return m, s, q, o, sh


def view_errors(options, model, views, picks, degree: int, background, sigma: float,
                hidden_rows) -> np.ndarray:
    """Per option (a carried object), the summed mean L1 of the `views` `picks` drawn by the
    model, its `hidden_rows` transparent, with that object (as `fit_objects` draws it)."""
    from nehad.splat.rasterize import render_torch

    hidden = torch.as_tensor(np.asarray(hidden_rows, np.int64))
    errors = np.zeros(len(options))
    with torch.no_grad():
        for k in picks:
            t = float(views.times[k])
            cloud = _held_cloud(model, t, hidden)
            for j, option in enumerate(options):
                res = render_torch(*_with_objects(cloud, [option], t, sigma), views.cameras[k],
                                   background=background, sh_degree=degree)
                errors[j] += float((res.rgb - views.images[k]).abs().mean())
    return errors


def materialise(obj: CarriedObject, field, like, sigma: float,
                seeds: torch.Tensor | None = None) -> tuple[dict, torch.Tensor]:
    """The object's members as canonical Gaussian parameters (GaussianParameters.NAMES): K per
    knot, living `sigma` around the knot's time and moving with its velocity, each placed so
    that the deformation field takes it to the fitted place, scale and rotation at its own time
    (`nehad.placement.solve_places`, with `seeds` (n K, 3) as other starting places), its
    velocity less the field's own motion of it there; `like`: the model's GaussianParameters
    (the shapes of their tensors). Returns (the parameters, (n K,) the distance left between
    each member's place and the fitted one: where the field folds space, a place may have no
    canonical point that it takes there)."""
    from nehad.placement import field_velocity, solve_places

    k, n = obj.offsets.shape[0], len(obj.times)
    with torch.no_grad():
        offs, swirl, turned = obj.placed(np.arange(n))
        want_mu = (torch.as_tensor(obj.points, dtype=torch.float32)[:, None] + offs).reshape(-1, 3)
        t_eq = torch.as_tensor(np.repeat(obj.times, k), dtype=torch.float32).reshape(-1, 1)
        reach = torch.full((n * k,), 0.2 * obj.radius)
        mu, ls, q, miss = solve_places(field, want_mu, obj.log_scales.repeat(n, 1),
                                       turned.reshape(-1, 4), t_eq, seeds, reach, neighbours=k)
        velocity = ((torch.as_tensor(obj.velocities, dtype=torch.float32)[:, None]
                     + swirl).reshape(-1, 3) - field_velocity(field, mu, ls, q, t_eq, sigma))
        shape = lambda name: (n * k,) + tuple(getattr(like, name).shape[1:])  # noqa: E731
        return {"means": mu, "log_scales": ls, "quats": q,
                "opacity_logits": obj.opacity_logits.detach().repeat(n, 1).reshape(
                    shape("opacity_logits")),
                "sh_dc": obj.sh_dc.detach().repeat(n, 1, 1), "sh_rest": torch.zeros(
                    shape("sh_rest")),
                "mu_eq": mu.clone(), "t_eq": t_eq.reshape(shape("t_eq")),
                "velocity": velocity.reshape(shape("velocity")),
                "life_rate": torch.full(shape("life_rate"), 1.0 / sigma)}, miss


def nearest_seeds(obj: CarriedObject, model, rows: np.ndarray) -> torch.Tensor | None:
    """(n K, 3): for each member of each knot, the canonical mean of the Gaussian of `rows`
    that the model draws nearest the member's fitted place at the knot's time (`materialise`'s
    other starting places); None without rows."""
    if not len(rows):
        return None
    k = obj.offsets.shape[0]
    index = torch.as_tensor(np.asarray(rows, np.int64))
    offs = obj.placed(np.arange(len(obj.times)))[0]
    out = torch.empty((len(obj.times) * k, 3))
    with torch.no_grad():
        canonical = model.gaussians.means[index]
        for i, t in enumerate(obj.times):
            want = torch.as_tensor(obj.points[i], dtype=torch.float32) + offs[i]
            drawn = model.means_at(float(t), index)
            out[i * k:(i + 1) * k] = canonical[torch.cdist(want, drawn).argmin(1)]
    return out


__all__ = ["CarriedObject", "fit_objects", "materialise", "nearest_seeds",
           "objects_from_tracks", "refit_unseen", "view_errors"]
