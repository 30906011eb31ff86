"""Objects that spin faster than the field follows, found for the carried-objects stage
(docs/training.md, "Objects that spin").

The deformation field's time axis has a few dozen cells; an object that turns a radian a cell
is fitted at each training time but not between them (the stress thin rod: +10 to +15 dB over a
blank image on its training views, under +5 on the held-out ones, which lie in gaps where it
turns 84 degrees). Such an object is found whole on the final model by hiding what moves: the
training views are rendered with every Gaussian that the field moves more than
`MOVING_EXTENT` of the scene's extent over time made transparent, and what is then unexplained
are the moving objects' silhouettes, followed as tracks (`nehad.tracks`). A track whose blobs'
shapes turn with a spin (`nehad.spin.estimate_spin`) becomes a carried object that turns with
it, fitted and judged in place of the field's Gaussians about its path (`nehad.carry_stage`).
"""

from __future__ import annotations

import numpy as np
import torch

#: A Gaussian that the field moves more than this fraction of the scene's extent over the time
#: grid counts as moving (the export's static split allows a thousandth).
MOVING_EXTENT = 0.01

#: Times sampled when measuring how far the field moves a Gaussian.
TIME_SAMPLES = 49

#: The unexplained pixels are closed (`nehad.tracks.find_blobs`) with a disc this fraction of
#: the image wide (7 pixels at 200): with every moving Gaussian hidden the backdrop alone is
#: drawn, and a body with stripes of the backdrop's colour falls apart into one blob per
#: stripe of its other colour (the stress suite's striped box: tracks of 8-22 blobs, none
#: spinning; one of 37 blobs, spinning at 12.2 rad per unit of time about an axis 2 degrees
#: from the true one, closed).
CLOSE_FRACTION = 0.035


def moving_rows(model) -> np.ndarray:
    """Rows of the model's Gaussians the field (with their drift) moves more than
    MOVING_EXTENT of the scene's extent over TIME_SAMPLES times in [0, 1], and the mortal ones."""
    g = model.gaussians
    rows = torch.arange(len(g))
    with torch.no_grad():
        ref = model.means_at(0.5, rows)
        far = torch.zeros(len(g))
        for t in np.linspace(0.0, 1.0, TIME_SAMPLES):
            far = torch.maximum(far, (model.means_at(float(t), rows) - ref).norm(dim=1))
    moving = far.numpy() > MOVING_EXTENT * float(model.field.extent)
    return np.nonzero(moving | g.mortal().numpy())[0]


def moving_tracks(model, views, degree: int, background, carve_cfg, moving: np.ndarray):
    """(tracks, cameras) of the training `views`' moving objects, whole: what is unexplained
    with the `moving` rows transparent, closed (`CLOSE_FRACTION`), followed as tracks."""
    from nehad.tracks import TrackSettings, find_blobs, fit_tracks
    from nehad.views import render_views, transparent

    with transparent(model.gaussians, moving):
        cams, targets, alphas, drawn = render_views(model, True, range(len(views.times)), views,
                                                    degree, background)
    close = int(round(CLOSE_FRACTION * min(targets[0].shape[:2])))
    blobs = find_blobs(cams, np.asarray(views.times, np.float64), targets, alphas,
                       [d.rgb for d in drawn], residual=carve_cfg.residual,
                       close_px=close + 1 - close % 2)
    return fit_tracks(cams, blobs, TrackSettings(max_tracks=carve_cfg.max_tracks)), cams


def spinning_tracks(model, views, degree: int, background, carve_cfg, spacing: float,
                    moving: np.ndarray, found=None):
    """(tracks, spins, cameras) of the training `views`' moving objects (`moving_tracks`, or
    `found`, what it returned) of at least `carve.carry_min_blobs` blobs whose shapes show a
    spin, the pieces of one spinning body joined (`join_spinning`)."""
    from nehad.tracks import TrackSettings

    tracks, cams = found or moving_tracks(model, views, degree, background, carve_cfg, moving)
    pieces = join_spinning(tracks, cams, spacing, TrackSettings().max_gap)
    field_rows = np.setdiff1d(moving, np.nonzero(model.gaussians.mortal().numpy())[0])
    pieces = [(track, spin) if spin.spins or len(track.blobs) < carve_cfg.carry_min_blobs
              else _round_spin(model, track, cams, views, spacing, spin, field_rows)
              for track, spin in pieces]
    pieces = join_round(pieces, cams, views, spacing, TrackSettings().max_gap)
    kept = [(track, spin) for track, spin in pieces
            if spin.spins and len(track.blobs) >= carve_cfg.carry_min_blobs]
    return [k[0] for k in kept], [k[1] for k in kept], cams


#: A body whose blobs' shapes show no spin is searched for one in its texture
#: (`texture_spin`) when its spread's least variance is at least this fraction of its largest:
#: a round body, which `nehad.texture_spin` takes as a ball.
ROUND = 0.5


def _round_spin(model, track, cams, views, spacing: float, shape_spin, field_rows):
    """(track, spin) of a body whose shape shows no spin: where it is round, its track on the
    field's path of it (`field_path`) and its spin from its texture (`texture_spin`)."""
    radius = ball_radius(shape_spin)
    if radius is None:
        return track, shape_spin
    on_field = field_path(model, track, radius, field_rows, spacing)
    return on_field, texture_spin(on_field, cams, views, spacing, shape_spin)


def join_round(pieces, cams, views, spacing: float, max_gap: float) -> list:
    """`pieces` ((track, spin) each) with the pieces of one round spinning body joined: a piece
    that starts before another ends (or within `max_gap` after), spinning alike (within a
    tenth), whose path at the start of the later one (the field's, `field_path`) is within
    half its radius of the earlier one's. The tracker may follow a body twice, or hand it from
    one track to another where another object passes: the stress checkered sphere was two
    tracks, over 0.01-0.78 and 0.67-0.95 of time, and carried as two it would be drawn twice
    where they overlap. The joined track has the blobs of both (the earlier one's where both
    saw a view) and its spin is found again from them."""
    from nehad.tracks import Track

    out = []
    for track, spin in sorted(pieces, key=lambda p: p[0].times[0]):
        for i, (prev, prev_spin) in enumerate(out):
            if not (spin.round and prev_spin.round and spin.spins and prev_spin.spins
                    and _same_spin(spin, prev_spin)
                    and track.times[0] <= prev.times[-1] + max_gap):
                continue
            at = track.times[:1]
            if np.linalg.norm(prev.smooth_at(at)[0] - track.smooth_at(at)[0]) > (
                    0.5 * ball_radius(spin)):
                continue
            views_seen = {b.view for b in prev.blobs}
            later = [k for k, b in enumerate(track.blobs) if b.view not in views_seen]
            order = np.argsort(np.concatenate([prev.times, track.times[later]]), kind="stable")
            both = Track([(prev.blobs + [track.blobs[k] for k in later])[k] for k in order],
                         np.concatenate([prev.times, track.times[later]])[order],
                         np.concatenate([prev.points, track.points[later]])[order],
                         np.concatenate([prev.velocities, track.velocities[later]])[order])
            out[i] = (both, texture_spin(both, cams, views, spacing, prev_spin))
            break
        else:
            out.append((track, spin))
    return out


def ball_radius(shape_spin) -> float | None:
    """The radius of the ball a round body's blobs show (discs of a ball of radius r fit a
    spread of r^2/4 each way), or None where its spread's least variance is under ROUND of its
    largest."""
    values = np.linalg.eigvalsh(shape_spin.spread)
    if not values[0] > ROUND * values[-1] > 0.0:
        return None
    return 2.0 * float(np.sqrt(values.mean()))


#: The field's Gaussians that draw a round body (`field_path`) are those within its radius of
#: its track's path at half or more of this many times across the track, and there must be at
#: least FIELD_PATH_ROWS of them.
FIELD_PATH_TIMES = 24
FIELD_PATH_ROWS = 16


def field_path(model, track, radius: float, rows: np.ndarray, spacing: float):
    """The track with its samples on the path the field draws the body along: at each sample's
    time, the opacity-weighted centroid of the field's `rows` that draw it (those within
    `radius` of the track's path at half of FIELD_PATH_TIMES times or more), its velocity their
    centroid's over a frame `spacing`; the track itself where fewer than FIELD_PATH_ROWS draw
    it. One view a time fixes a blob's ray, not its depth, and the tracker's path, fitted to a
    few rays at a time, cuts the corners of a bounce and follows blobs of other objects merged
    with it: on the stress checkered sphere it was 0.08 off the sphere's centre at its blobs'
    times (median; 0.9 at the 90th percentile, radius 0.35), the field's centroid 0.03 (0.08;
    docs/results.md, 2026-12-03)."""
    from dataclasses import replace
    from types import SimpleNamespace

    times = np.linspace(float(track.times[0]), float(track.times[-1]), FIELD_PATH_TIMES)
    stub = SimpleNamespace(times=times, points=track.smooth_at(times)[0], radius=radius)
    near = times_near_path(model, stub, rows, times)[0]
    body = rows[2 * near >= len(times)]
    if len(body) < FIELD_PATH_ROWS:
        return track
    index = torch.as_tensor(body)
    with torch.no_grad():
        weights = torch.sigmoid(model.gaussians.opacity_logits[index]).reshape(-1, 1)

        def centroid(t: float) -> np.ndarray:
            return ((model.means_at(float(t), index) * weights).sum(0) / weights.sum()).numpy()

        points = np.stack([centroid(t) for t in track.times])
        velocities = np.stack([centroid(t + 0.5 * spacing) - centroid(t - 0.5 * spacing)
                               for t in track.times]) / spacing
    return replace(track, points=points, velocities=velocities, end_accelerations=None)


#: A blob whose ray misses the body's path by more than this many radii is not its view
#: (`texture_spin`).
RAY_MISS = 0.25


def texture_spin(track, cams, views, spacing: float, shape_spin):
    """A round body's spin from its texture (`nehad.texture_spin`) where its blobs' shapes
    found none (`shape_spin`, whose spread says how round it is and how large:
    `ball_radius`); `shape_spin` itself for a body that is not round. Its centre at each view
    is on the ray through its blob's centroid, at the depth of the track's path there (the
    field's, `field_path`), and a blob whose ray misses the path by more than RAY_MISS radii
    is left out (a blob of another object, or of two merged). On the stress checkered
    sphere, the tracker's own path (0.08 off its centre at its blobs' times, median, radius
    0.35) showed no spin (0.98 of no spin's misfit); on the rays, its rate within 1% and
    its axis within 3 degrees (docs/results.md, 2026-12-03)."""
    from nehad.texture_spin import estimate_texture_spin, surface_samples

    radius = ball_radius(shape_spin)
    if radius is None:
        return shape_spin
    path, _ = track.smooth_at(np.array([b.time for b in track.blobs]))
    centres, seen = [], []
    for b, point in zip(track.blobs, path):
        on_ray = b.origin + b.direction * float((point - b.origin) @ b.direction)
        if np.linalg.norm(point - on_ray) <= RAY_MISS * radius:
            centres.append(on_ray)
            seen.append((cams[b.view], b.time, views.images[b.view].numpy()))
    return estimate_texture_spin(surface_samples(seen, centres, radius), spacing, radius)


def _spin_of(track, cams, spacing: float):
    from nehad.spin import estimate_spin

    points, _ = smooth_path(track, np.array([b.time for b in track.blobs]))
    return estimate_spin(track.blobs, cams, points, spacing)


def join_spinning(tracks, cams, spacing: float, max_gap: float) -> list:
    """(track, spin) of each track, where a track that starts after a spinning one ends, where
    that one's path, carried on, is then (within its body's half length), is joined to it:
    - a spinning piece, within `max_gap` and with its spin (within a tenth): a spinning body's
      centroid wanders with its outline, its blobs miss the tracker's gates and its track
      breaks (the stress thin rod's into pieces of 57 and 21 blobs a frame apart);
    - any other piece, after a gap no longer than the spinning one was followed (nor than
      `max_gap`), when the pieces joined still show the first one's spin (within a tenth):
      while another object passes before a spinning one, their blobs merge and its track
      breaks, and a piece of a few blobs, or of blobs shaped by the other object, shows no
      spin or another (the stress suite's striped box: pieces of 37 blobs over 0.01-0.58,
      8 blobs merged with the checkered sphere passing before it, and 7 blobs over
      0.88-0.95 where the first one's path puts the box, 0.04 from it)."""
    out = []
    for track in sorted(tracks, key=lambda tr: tr.times[0]):
        spin = _spin_of(track, cams, spacing)
        for i, (prev, prev_spin) in enumerate(out):
            joined = _joined(prev, prev_spin, track, spin, cams, spacing, max_gap)
            if joined is not None:
                out[i] = joined
                break
        else:
            out.append((track, spin))
    return out


def _joined(prev, prev_spin, track, spin, cams, spacing: float, max_gap: float):
    """(the two tracks as one, its spin) when `track` continues the spinning `prev`
    (`join_spinning`), else None."""
    from nehad.tracks import Track

    if not prev_spin.spins:
        return None
    agrees = spin.spins and _same_spin(spin, prev_spin)
    gap = track.times[0] - prev.times[-1]
    if not 0.0 < gap <= (max_gap if agrees else max(max_gap, prev.times[-1] - prev.times[0])):
        return None
    half = float(np.sqrt(3.0 * max(np.linalg.eigvalsh(prev_spin.spread)[-1], 0.0)))
    ends = (smooth_path(prev, track.times[:1])[0][0] - smooth_path(track, track.times[:1])[0][0])
    if np.linalg.norm(ends) > half:
        return None
    both = Track(prev.blobs + track.blobs, np.concatenate([prev.times, track.times]),
                 np.concatenate([prev.points, track.points]),
                 np.concatenate([prev.velocities, track.velocities]))
    both_spin = _spin_of(both, cams, spacing)
    if not (agrees or (both_spin.spins and _same_spin(both_spin, prev_spin))):
        return None
    return both, both_spin


def _same_spin(a, b) -> bool:
    """The two spins' angular velocities agree within a tenth of the faster."""
    rate = max(float(np.linalg.norm(a.omega)), float(np.linalg.norm(b.omega)))
    return float(np.linalg.norm(a.omega - b.omega)) <= 0.1 * rate


#: Half the window of time, either side of a knot, over which a spinning object's path is
#: fitted (`smooth_path`). Its local motion is left to the fit's correction of the path
#: (`nehad.carry.CarriedObject.path_fix`, a value every few frame spacings): with 0.08 the
#: path still followed the stress thin rod's wandering centroid, which the correction, linear
#: across a held-out gap, cannot undo there (0.019 off the rod's fixed centre across its axis
#: at the test times, median; 0.009 with 0.25, two wander periods of its half turn).
PATH_WINDOW = 0.25


def smooth_path(track, times: np.ndarray, window: float = PATH_WINDOW):
    """(points (m, 3), velocities (m, 3)) of the track at `times`, each from a quadratic motion
    fitted to the rays of its blobs within `window` of that time (`nehad.tracks.fit_motion`;
    widened until they fix one); past the track's ends, along the end's velocity (a quadratic
    fitted to one side only runs off). A spinning body's blob centroid wanders about its centre as
    its shading and outline turn (the stress thin rod's by 0.05-0.1 of its length, at local
    velocities of up to 12 units a unit of time for a rod that does not move): a track's own
    samples, fitted to six blobs each, follow that wander, and across a held-out gap a curve
    through them overshoots by a third of the rod's length. Past an end the path runs on along
    a straight line fitted to the blobs within twice `window` of it: a quadratic's slope at
    its window's edge follows the wander (the thin rod's took its carried copy 0.11 off its
    fixed centre 0.025 of time past its last training view)."""
    blob_times = np.array([b.time for b in track.blobs])
    times = np.asarray(times, np.float64)
    inside = np.clip(times, blob_times.min(), blob_times.max())
    points, velocities = np.empty((len(times), 3)), np.empty((len(times), 3))
    for i, t in enumerate(inside):
        coef = _local_motion(track, blob_times, float(t), window, 2)
        if coef is None:
            points[i], velocities[i] = (x[0] for x in track.smooth_at(np.array([t])))
        else:
            points[i], velocities[i] = coef[0], coef[1]
    ends = {}
    for i in np.nonzero(times != inside)[0]:
        if inside[i] not in ends:
            coef = _local_motion(track, blob_times, float(inside[i]), 2.0 * window, 1)
            ends[inside[i]] = velocities[i] if coef is None else coef[1]
        velocities[i] = ends[inside[i]]
    return points + velocities * (times - inside)[:, None], velocities


def _local_motion(track, blob_times, t: float, window: float, degree: int):
    """`nehad.tracks.fit_motion` of the track's blobs within `window` of t (widened until they
    fix one), or None."""
    from nehad.tracks import fit_motion

    coef, reach = None, window
    while coef is None and reach < 4.0:
        near = [b for b, bt in zip(track.blobs, blob_times) if abs(bt - t) <= reach]
        coef = fit_motion(near, t, degree) if len(near) >= 6 else None
        reach *= 1.5
    return coef


def rows_along(model, obj, rows: np.ndarray, sigma: float, reaches=(1.0,),
               samples: int = 24) -> list[np.ndarray]:
    """Per reach of `reaches`, the `rows` within that many times the object's radius of its
    path at most of `samples` times across its span (1: the Gaussians that draw it now); the
    field is evaluated once for all of them."""
    lo, hi = obj.span(sigma)
    times = np.linspace(max(lo, float(obj.times[0])), min(hi, float(obj.times[-1])), samples)
    return [rows[2 * n >= samples] for n in times_near_path(model, obj, rows, times, reaches)]


def times_near_path(model, obj, rows: np.ndarray, times, reaches=(1.0,)) -> np.ndarray:
    """(len(reaches), len(rows)) at how many of `times` each of the `rows` is within that reach
    times the object's radius of its path (linear between its knots); the field is evaluated
    once a time for all of them."""
    limits = np.asarray(reaches, np.float64)[:, None] * obj.radius
    near = np.zeros((len(limits), len(rows)), np.int64)
    index = torch.as_tensor(rows)
    with torch.no_grad():
        for t in times:
            path = np.array([np.interp(t, obj.times, obj.points[:, j]) for j in range(3)])
            at = model.means_at(float(t), index).numpy()
            near += np.linalg.norm(at - path, axis=1)[None] <= limits
    return near


__all__ = ["MOVING_EXTENT", "PATH_WINDOW", "ROUND", "ball_radius", "field_path", "join_round",
           "join_spinning",
           "moving_rows", "moving_tracks", "rows_along", "smooth_path", "spinning_tracks",
           "texture_spin", "times_near_path"]
