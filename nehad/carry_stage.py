"""The carried-objects stage after a run's last step (`carve.carry_steps`; `nehad.carry` says what
a carried object is and why): find what the model draws only with its chains, fit each such object
as one appearance along its track, and write it in where the held-out views prefer it."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import torch

from nehad.carry import (
    fit_objects,
    materialise,
    nearest_seeds,
    objects_from_tracks,
    refit_unseen,
    view_errors,
)
from nehad.views import transparent

#: A written-out member the field cannot take within this many object radii of its fitted place
#: is left out (`nehad.carry.materialise`).
MISS_RADII = 0.1

#: The most a spinning object turns between two of its written-out copies, in radians; a round
#: body whose spin is found in its texture (`nehad.texture_spin`), carried with
#: `carve.carry_texture_members`, at most MAX_TURN_ROUND. The stress suite's checkered sphere,
#: carried on its true path and spin, scored +14.9 dB over blank on its pixels at the test
#: times with 96 members at 0.1 rad (18k Gaussians), +14.8 with 128 at 0.25 (9.7k), +16.2 with
#: 256 at 0.1 (48k); the field's sphere +10.7. The stress thin rod with 128 members (and the
#: round bodies' choice of what to replace): +8.2 in its worst quarter at 0.1 rad, +4.0 at
#: 0.25 (+8.8 with 24 at 0.1; docs/results.md, 2026-12-03).
MAX_TURN = 0.1
MAX_TURN_ROUND = 0.25

#: A carried object's path is corrected by the fit at points this many frame spacings apart
#: (`nehad.carry.CarriedObject.path_fix`), and the knots its track did not see are then placed
#: from the corrected path (`nehad.carry.refit_unseen`): the stress thin rod's smoothed path,
#: its blobs' centroids, was 0.02-0.10 off its fixed centre at the test times (its thickness
#: 0.06), and an occluder variant's sphere, partly behind a wall's end over its last training
#: views, 0.05-0.41 radii off there (0.04-0.25 corrected; docs/training.md, step 6 of
#: "Objects carried along their tracks").
PATH_FIX_FRAMES = 5

#: The field's Gaussians within this many radii of a spinning object's path are the wider
#: choice of what it replaces: about the stress thin rod, white Gaussians that trimmed the
#: field's smeared rod in some training views circle 0.4-1.05 from its centre (its half length
#: 0.7) and, the field's rod hidden, cut holes in the carried one.
WIDE_RADII = 2.0

#: A short track is carried when the render covers this many of its blobs less than
#: `carve.carry_absent_cover` (`carried_tracks`): in that many views nothing is drawn where the
#: object is seen.
ABSENT_BLOBS = 3

#: Chain Gaussians this close to a carried object's path at their own time, in object radii, are
#: what the object replaces.
NEAR_RADII = 2.0

#: The field's Gaussians within the object's radius of its path at this many of its seen knots
#: draw it there (`field_rows_on_path`).
FIELD_DRAWN_KNOTS = 2


def undrawn_tracks(model, views, degree: int, background, carve_cfg, hidden_rows):
    """The tracks (`nehad.tracks.fit_tracks`) of what the training `views` show and the model
    does not draw with its `hidden_rows` (the chains) transparent, those `carried_tracks`
    keeps; each blob placed at the centroid of the object's pixels about it, not only of those
    the render misses (`find_blobs`' `widen_tol`, the tracker's colour tolerance)."""
    from nehad.tracks import TrackSettings, find_blobs, fit_tracks
    from nehad.views import render_views

    with transparent(model.gaussians, hidden_rows):
        cams, targets, alphas, drawn = render_views(model, True, range(len(views.times)), views,
                                                    degree, background)
    settings = TrackSettings(max_tracks=carve_cfg.max_tracks)
    blobs = find_blobs(cams, np.asarray(views.times, np.float64), targets, alphas,
                       [d.rgb for d in drawn], residual=carve_cfg.residual,
                       covers=[d.alpha for d in drawn], widen_tol=settings.colour_tol)
    tracks = fit_tracks(cams, blobs, settings)
    return carried_tracks(tracks, carve_cfg.carry_min_blobs, carve_cfg.carry_absent_cover), cams


def carried_tracks(tracks, min_blobs: int, absent_cover: float) -> list:
    """The tracks worth carrying: those of at least `min_blobs` blobs, and the shorter ones over
    whose blobs the render's alpha (`nehad.tracks.Blob.cover`) is under `absent_cover` on the
    mean or in ABSENT_BLOBS of them.

    A short track is either an object seen in few views (a fast one) or a fragment of a texture
    the field draws wrong; only the first is missing from the render. On the stress suite's
    spinning textures the 6-11 blob tracks of the model before the stage were covered
    0.55-0.95 on the mean, the fast ball variant's 7-blob track 0.00 (docs/results.md,
    2026-11-30). A missing object seen partly before a drawn backdrop (a floor, a box) is
    covered there by the backdrop, and only where nothing lies behind it is it uncovered: a
    fast ball of 9 blobs, 5 of them before the empty background (covered 0.00) and 4 before a
    box (0.52-1.00), 0.37 on the mean (docs/results.md, 2026-12-02). A texture drawn wrong is
    drawn over all its blobs."""
    out = []
    for t in tracks:
        covers = np.array([b.cover for b in t.blobs], np.float64)
        if (len(t.blobs) >= min_blobs or np.mean(covers) < absent_cover
                or int((covers < absent_cover).sum()) >= ABSENT_BLOBS):
            out.append(t)
    return out


def near_rows(obj, means_at_own_time: np.ndarray, t_eq: np.ndarray, rows: np.ndarray,
              sigma: float) -> np.ndarray:
    """The `rows` (chain Gaussians; their places at their own times and their times given)
    within NEAR_RADII object radii of the object's path at their time, inside its span."""
    lo, hi = obj.span(sigma)
    t = t_eq[rows]
    inside = (t >= lo) & (t <= hi)
    path = np.stack([np.interp(t, obj.times, obj.points[:, j]) for j in range(3)], axis=1)
    close = np.linalg.norm(means_at_own_time[rows] - path, axis=1) <= NEAR_RADII * obj.radius
    return rows[inside & close]


def field_rows_on_path(model, obj, field_rows: np.ndarray) -> np.ndarray:
    """The field's moving `field_rows` that draw the object: within its radius of its path at
    FIELD_DRAWN_KNOTS or more of the knots its track saw. Where the field draws an object over
    part of its path and parks the same Gaussians out of sight elsewhere (inside an occluder),
    they cross open space on their way at held-out times: a second sphere a sphere's width
    from the carried one (an occluder variant; docs/results.md, 2026-12-02 afternoon)."""
    from nehad.spin_tracks import times_near_path

    if not len(field_rows):
        return field_rows
    seen = obj.seen or (obj.times[0], obj.times[-1])
    knots = obj.times[(obj.times >= seen[0] - 1e-9) & (obj.times <= seen[1] + 1e-9)]
    return field_rows[times_near_path(model, obj, field_rows, knots)[0] >= FIELD_DRAWN_KNOTS]


def carry_stage(model, train_views, val_views, carve_cfg, degree: int, background,
                spacing: float, time_range, seed: int = 0) -> dict:
    """Find, fit and judge the carried objects of a trained model (module docstring): what it
    draws only with its chains, and what spins faster than its field follows
    (`nehad.spin_tracks`, with `carve.carry_spin`); the accepted ones are appended to its
    Gaussians and the Gaussians about their paths made transparent. Returns what it did
    (tracks found, objects kept, Gaussians added)."""
    g = model.gaussians
    mortal = np.nonzero(g.mortal().numpy())[0]
    if val_views is None or not len(val_views.times) or spacing <= 0:
        return {}
    rng = np.random.default_rng(seed)
    tracks, cams, found, moving, whole = _tracks_to_carry(model, train_views, degree, background,
                                                          carve_cfg, mortal)
    spun, field_rows = [], np.setdiff1d(moving, mortal)
    knot = spacing * carve_cfg.carry_knots
    sigma = carve_cfg.life * knot
    objects = objects_from_tracks(tracks, cams, knot, time_range, carve_cfg.carry_members, rng,
                                  fix_every=PATH_FIX_FRAMES * spacing)
    log = fit_objects(objects, model, train_views, degree, background, sigma,
                      carve_cfg.carry_steps, mortal, rng)
    along, lives = [[np.zeros(0, np.int64)]] * len(objects), [sigma] * len(objects)
    if carve_cfg.carry_spin:
        spun, spun_along, spun_lives = _spinning_objects(
            model, train_views, degree, background, carve_cfg, spacing, time_range, mortal,
            moving, field_rows, rng, whole)
        objects, along, lives = objects + spun, along + spun_along, lives + spun_lives
    if not objects:
        return {"carry_tracks": len(found), "carry_spinning": 0}
    choose = _gap_chooser(model, val_views, degree, background, mortal, sigma)
    for obj in objects:
        refit_unseen(obj, choose)
    with torch.no_grad():
        t_eq = g.t_eq.detach().reshape(-1).numpy().astype(np.float64)
        own = np.zeros((len(g), 3))
        for t in np.unique(t_eq[mortal]):
            rows = mortal[t_eq[mortal] == t]
            own[rows] = model.means_at(float(t), torch.as_tensor(rows)).numpy()
    judge = _Judge(model, val_views, degree, background, train_views)
    did = {"carry_tracks": len(found), "carry_completed": sum(
               all(t is not f for f in found) for t in tracks),
           "carry_spinning": len(spun), "carry_kept": 0,
           "carry_gaussians": 0, "carry_knots_trimmed": 0, "carry_kept_beside_chains": 0,
           "carry_placement_radii": 0.0, "carry_unplaced": 0, "carry_replaced_wider": 0,
           "carry_replaced_field": 0}
    for obj, extras, life in zip(objects, along, lives):
        options = [  # each: the rows knots a..b replace, one way
            lambda a, b, o=obj, extra=extra, life=life: np.union1d(
                near_rows(_knots(o, a, b), own, t_eq, mortal, life), extra) for extra in extras]
        spins = any(len(extra) for extra in extras)
        drawn = np.zeros(0, np.int64) if spins else field_rows_on_path(model, obj, field_rows)
        _write_in(model, obj, judge, options, life, did, field_rows, spins, drawn)
    did["carry_placement_radii"] = round(did["carry_placement_radii"], 4)
    did["carry_fit_l1"] = [round(v, 6) for v in log]
    return did


def _tracks_to_carry(model, views, degree: int, background, carve_cfg, mortal):
    """(tracks, cameras, the tracks `undrawn_tracks` found, the moving rows, the moving
    objects' tracks (`nehad.spin_tracks.moving_tracks`; None when not looked for)): what the
    model draws only with its chains, each completed by the moving object's whole track it is
    part of (`nehad.tracks.completed`); moving rows and whole tracks are looked for where
    there is a track or `carve.carry_spin` asks for them (`_spinning_objects` takes them)."""
    tracks, cams = undrawn_tracks(model, views, degree, background, carve_cfg, mortal)
    found, moving, whole = list(tracks), np.asarray(mortal, np.int64), None
    if carve_cfg.carry_spin or tracks:
        from nehad.spin_tracks import moving_rows, moving_tracks
        from nehad.tracks import TrackSettings, completed

        moving = moving_rows(model)
        whole = moving_tracks(model, views, degree, background, carve_cfg, moving)
        tracks = completed(tracks, whole[0], cams, TrackSettings(max_tracks=carve_cfg.max_tracks))
    return tracks, cams, found, moving, whole


def _gap_chooser(model, views, degree: int, background, hidden_rows, sigma: float):
    """`nehad.carry.refit_unseen`'s choice of a path across a gap of a track: the option that
    brings the held-out `views` inside the gap closest to their targets, drawn as the fit draws
    them (the chains, `hidden_rows`, transparent); None where no held-out view falls there."""
    def choose(obj, span, options):
        picks = [k for k, t in enumerate(views.times) if span[0] < t < span[1]]
        if not picks:
            return None
        return int(np.argmin(view_errors(options, model, views, picks, degree, background,
                                         sigma, hidden_rows)))
    return choose


def _spinning_objects(model, views, degree, background, carve_cfg, spacing, time_range,
                      mortal, moving, field_rows, rng, found=None):
    """The spinning objects (`nehad.spin_tracks`; `moving`: the rows the field moves and the
    mortal ones, `field_rows`: the former only), each fitted with the field's Gaussians about
    its path and the chains transparent; (objects, per object the field's rows it may replace
    (those within its radius of its path, and those within WIDE_RADII radii: `_kept_knots`
    chooses), each one's life sigma). A spinning object's knots are at most MAX_TURN of its
    turn apart: a copy moves in a straight line over its life, and the tip of a body turning a
    radian over it would leave the body's place by a quarter of its radius. `found`: the
    moving objects' tracks, `nehad.spin_tracks.moving_tracks`, when already found."""
    from nehad.spin_tracks import rows_along, spinning_tracks

    tracks, spins, cams = spinning_tracks(model, views, degree, background, carve_cfg, spacing,
                                          moving, found)
    objects, along, lives = [], [], []
    for track, spin in zip(tracks, spins):
        members, turn = ((carve_cfg.carry_texture_members, MAX_TURN_ROUND) if spin.round else
                         (carve_cfg.carry_members, MAX_TURN))
        knot = min(spacing * carve_cfg.carry_knots,
                   turn / max(float(np.linalg.norm(spin.omega)), 1e-9))
        life = carve_cfg.life * knot
        obj = objects_from_tracks([track], cams, knot, time_range, members, rng, [spin],
                                  PATH_FIX_FRAMES * spacing)[0]
        rows, wide = rows_along(model, obj, field_rows, life, (1.0, WIDE_RADII))
        fit_objects([obj], model, views, degree, background, life, carve_cfg.carry_steps,
                    np.union1d(mortal, rows), rng)
        objects.append(obj)
        along.append([rows] if len(wide) == len(rows) else [rows, wide])
        lives.append(life)
    return objects, along, lives


def _write_in(model, obj, judge, options, sigma: float, did: dict, field_rows,
              everywhere: bool = False, drawn=()) -> None:
    """Append the object's members (`materialise`, from the places of the field's moving
    `field_rows` too; those the field cannot place left out), judge them (`_kept_knots`), and
    keep the knots judged good, the rows they replace (one of `options`) made transparent when
    that was judged better (`everywhere`: they include rows that draw at every time, the
    field's, judged on every held-out view; `drawn`: the field's rows that draw the object
    over part of its path, which it may replace everywhere, `_in_place_of_field`); `did` counts
    what was done."""
    from nehad.densify import append_gaussians, keep_gaussians

    g = model.gaussians
    no_optimizer = SimpleNamespace(param_groups=[], state={})
    new, off = materialise(obj, model.field, g, sigma, nearest_seeds(obj, model, field_rows))
    placed = off <= MISS_RADII * obj.radius
    new = {name: value[placed] for name, value in new.items()}
    knot_of = np.repeat(np.arange(len(obj.times)), obj.offsets.shape[0])[placed.numpy()]
    did["carry_unplaced"] += int((~placed).sum())
    if bool(placed.any()):
        did["carry_placement_radii"] = max(did["carry_placement_radii"],
                                           float(off[placed].max()) / obj.radius)
    start = len(g)
    append_gaussians(g, no_optimizer, new)
    judge.forget()
    rows = np.arange(start, len(g))
    knots = _kept_knots(obj, judge, rows, knot_of, options, sigma, everywhere)
    if len(drawn):
        knots, options, replaced = _in_place_of_field(obj, judge, rows, knot_of, options, sigma,
                                                      drawn, knots)
        did["carry_replaced_field"] += int(replaced)
    keep = torch.ones(len(g), dtype=torch.bool)
    if knots is None:
        keep[start:] = False
    else:
        lo, hi, swap = knots
        keep[torch.as_tensor(rows[(knot_of < lo) | (knot_of > hi)])] = False
        if swap is not None:
            with torch.no_grad():
                g.opacity_logits[torch.as_tensor(options[swap](lo, hi))] = -30.0
        did["carry_kept"] += 1
        did["carry_gaussians"] += int(keep[start:].sum())
        did["carry_kept_beside_chains"] += int(swap is None)
        did["carry_replaced_wider"] += int(bool(swap))
        did["carry_knots_trimmed"] += len(obj.times) - (hi - lo + 1)
    keep_gaussians(g, no_optimizer, keep)
    judge.forget()


def _in_place_of_field(obj, judge, rows, knot_of, options, sigma: float, drawn, knots):
    """(knots, options, whether the field's `drawn` rows are replaced): `knots` (kept with one
    of `options`, `_kept_knots`) or the knots kept when the object also replaces `drawn` at
    every time, whichever brings every view, held-out and training, closer to its target.

    The field may draw an object over part of its path (its track then has a gap there, or
    ends) and keep the same Gaussians out of sight at other times, inside an occluder; between
    the two they cross open space, and at the held-out times there they are a second object
    beside the carried one. Hidden, the object is drawn where they drew it only if its knots
    reach there (`_kept_knots`, outwards from its seen span), so the choice is judged on the
    training views as well, which see the object there."""
    wider = [lambda a, b: np.union1d(options[0](a, b), drawn)]
    other = _kept_knots(obj, judge, rows, knot_of, wider, sigma, everywhere=True)
    if other is None or other[2] is None:
        return knots, options, False

    def hidden(kept, ways):
        if kept is None:
            return rows
        lo, hi, swap = kept
        out = rows[(knot_of < lo) | (knot_of > hi)]
        return out if swap is None else np.concatenate([out, ways[swap](lo, hi)])

    views = judge.every_view()
    if judge.error(views, hidden(other, wider)) < judge.error(views, hidden(knots, options)):
        return other, wider, True
    return knots, options, False


def _knots(obj, lo: int, hi: int):
    """The object with its knots lo..hi only (its path and span there)."""
    return replace(obj, times=obj.times[lo:hi + 1], points=obj.points[lo:hi + 1],
                   velocities=obj.velocities[lo:hi + 1])


def _kept_knots(obj, judge, rows, knot_of, options, sigma: float, everywhere: bool = False):
    """The knots (lo, hi) of a written-out object to keep and which of `options` gives the rows
    about them to hide (`swap`, None: none), or None. First those of the span its track saw:
    kept where the held-out views inside that span get closer to their targets with them,
    either in place of the chains they replace (`options[i](lo, hi)` hidden) or beside them,
    whichever is closest
    (where the field cannot place many of an object's copies, the chains still draw part of
    it: `nehad demo`'s bouncing ball); kept where no held-out view falls there, as a chain is.
    Then the seen span's ends are trimmed (`_trimmed_inwards`) and the knots past them added
    while the views there agree (`_extended_outwards`). With `everywhere` the rows replaced
    draw at every time (the field's Gaussians about a spinning object), so the first choice
    is judged on every held-out view: on a variant of the stress thin rod whose track was seen
    from t = 0.17 on, judged on the views of that span, the object replaced the field's rod
    and the rod was gone before it (+6.9 -> +0.0 dB over blank in the first quarter)."""
    seen = obj.seen or (obj.times[0], obj.times[-1])
    inside = np.nonzero((obj.times >= seen[0] - 1e-9) & (obj.times <= seen[1] + 1e-9))[0]
    if not len(inside):
        inside = [int(np.abs(obj.times - 0.5 * (seen[0] + seen[1])).argmin())]
    lo, hi = int(inside[0]), int(inside[-1])

    def error(views, a, b, swap, about=None):  # the views' error with knots a..b kept and
        out = rows[(knot_of < a) | (knot_of > b)]  # the rows about knots `about` (a..b) hidden
        return judge.error(views, hide=out if swap is None else
                           np.concatenate([out, options[swap](*(about or (a, b)))]))

    views, swap = judge.views_in((-np.inf, np.inf) if everywhere else seen), 0
    reach = sigma * (1.0 + 1e-6)
    if views:
        choices = list(range(len(options))) + [None]
        if everywhere and obj.round_spin:
            return _kept_everywhere(obj.times, judge, error, views, lo, hi, choices, reach,
                                    judge.error(views, hide=rows))
        errors = [error(views, lo, hi, c) for c in choices]
        if not min(errors) < judge.error(views, hide=rows):
            return None
        swap = choices[int(np.argmin(errors))]
    lo, hi = _trimmed_inwards(obj.times, judge, error, lo, hi, swap, reach)
    return (*_extended_outwards(obj.times, judge, error, lo, hi, swap, reach), swap)


def _kept_everywhere(times, judge, error, views, lo, hi, choices, reach, none: float):
    """`_kept_knots` for a round body whose spin its texture showed (the rows it may replace,
    the field's, draw at every time): each of the `choices` (which rows to hide, None: none)
    with its knots trimmed and grown from the seen span lo..hi, the one that brings the
    held-out `views` closest to their targets, if closer than without the object (`none`,
    their error). Judged on the seen span alone, hiding the field's own drawing of the body
    lost wherever the seen span does not reach: the stress checkered sphere, seen over
    0.008-0.95 of time, was kept beside the field's sphere, whose scrambled checkers showed
    through (+12.46 dB over blank on its pixels), though in place of it, its knots grown past
    the span, it brought the held-out views 11% closer to their targets than beside it
    (+13.26). The bodies whose shapes show their spin keep the choice on the seen span: so
    judged, with 128 members, the stress thin rod's worst quarter fell +8.8 -> +8.2; with 24,
    the striped box's +8.4 -> +7.4 (docs/results.md, 2026-12-03)."""
    best, best_error = None, none
    for choice in choices:
        a, b = _trimmed_inwards(times, judge, error, lo, hi, choice, reach)
        a, b = _extended_outwards(times, judge, error, a, b, choice, reach)
        value = error(views, a, b, choice)
        if value < best_error:
            best, best_error = (a, b, choice), value
    return best


def _trimmed_inwards(times, judge, error, lo, hi, swap, reach):
    """The seen knots lo..hi less those, from each end inwards, that no held-out view within
    `reach` of them judges and without which the training views there get closer to their
    targets, the rows the seen knots replace hidden either way (the chains and the field were
    fitted to the training views, so those views favour these rows over any carried copy;
    with the rows hidden, a knot where the object is fills the hole and a knot where it is
    gone draws on empty background). Where colliding spheres merge into one blob, scene3's
    blue sphere's track ran on past it, the copies over its last 0.015 of time drew it beside
    the cluster at those training views, and its path, run on past them, drew a second blue
    sphere at the test times after (docs/results.md, 2026-12-02 night)."""
    seen_knots = (lo, hi)
    for step in (-1, 1):
        while lo < hi:
            t = float(times[lo if step < 0 else hi])
            window = (t - reach, t + reach)
            views = [] if judge.views_in(window) else judge.trained_in(window)
            a, b = (lo + 1, hi) if step < 0 else (lo, hi - 1)
            if not views or not (error(views, a, b, swap, seen_knots)
                                 < error(views, lo, hi, swap, seen_knots)):
                break
            lo, hi = a, b
    return lo, hi


def _extended_outwards(times, judge, error, lo, hi, swap, reach):
    """The knots lo..hi grown knot by knot outwards, each kept while the views within `reach`
    of it (where its life window is over 0.6) get no further from their targets: a path
    extrapolated past its track's ends runs on where the object is gone (the stress fast ball
    after its landing, hidden under the floor). Those views are the held-out ones and the
    training ones (before 2026-12-02 night only those past the span the object was fitted on,
    `CarriedObject.fitted_span`): on a fast ball variant whose held-out views all lay
    elsewhere, the copies past its landing were kept and drew it at a test time where it was
    gone, though three training views there showed nothing (docs/results.md, 2026-12-01)."""
    for step in (-1, 1):
        while 0 <= (nxt := (lo if step < 0 else hi) + step) < len(times):
            t = float(times[nxt])
            window = (t - reach, t + reach)
            views = judge.views_in(window) + judge.trained_in(window)
            a, b = (nxt, hi) if step < 0 else (lo, nxt)
            if views and error(views, a, b, swap) > error(views, lo, hi, swap):
                break
            lo, hi = a, b
    return lo, hi


class _Judge:
    """Summed squared error of views with some rows made transparent: the held-out `views`
    and, after them, the `trained` ones (`trained_in`). Each view's Gaussians at its time are
    evaluated once (the deformation field) and kept until `forget` (the model's rows changed);
    a judgement zeroes the hidden rows' opacities in a copy."""

    def __init__(self, model, views, degree, background, trained=None):
        self.model, self.degree, self.background = model, degree, background
        self.held_out = len(views.times)
        extra = ([], [], []) if trained is None else (trained.cameras, trained.images,
                                                       trained.times)
        self.views = SimpleNamespace(cameras=list(views.cameras) + list(extra[0]),
                                     images=list(views.images) + list(extra[1]),
                                     times=list(views.times) + list(extra[2]))
        self.clouds = {}

    def views_in(self, span) -> list:
        """The held-out views whose times are in `span`."""
        return [k for k, t in enumerate(self.views.times[:self.held_out])
                if span[0] <= t <= span[1]]

    def trained_in(self, span) -> list:
        """The training views whose times are in `span`."""
        return [self.held_out + k for k, t in enumerate(self.views.times[self.held_out:])
                if span[0] <= t <= span[1]]

    def every_view(self) -> list:
        """Every view, held-out and trained."""
        return list(range(len(self.views.times)))

    def forget(self) -> None:
        self.clouds = {}

    def error(self, views, hide) -> float:
        from nehad.model import cloud_at
        from nehad.runtime.raster import render

        total, hide = 0.0, np.asarray(hide, np.int64)
        for k in views:
            if k not in self.clouds:
                self.clouds[k] = cloud_at(self.model, float(self.views.times[k]), self.degree)
            cloud = self.clouds[k]
            alpha = cloud.opacities.copy()
            alpha[hide] = 0.0
            rgb = render(replace(cloud, opacities=alpha), self.views.cameras[k],
                         self.background).rgb
            total += float(np.square(rgb - self.views.images[k].numpy()).sum())
        return total


__all__ = ["carry_stage", "near_rows", "undrawn_tracks"]
