"""Tracks of unexplained blobs: where an object that no Gaussian draws moves through the views
(docs/training.md, "Objects that are never created").

A small object that moves fast is seen by one camera per time in a MuJoCo rig, so no static
point explains it in two views and voting across views (nehad.carve) finds it only near one
time. Its residual does have a structure a static vote cannot use: in every view the object is
one *blob* of unexplained pixels, and the rays through the blobs of the views in time order pass
through one smooth 3D path x(t). A ray (origin c, unit direction d) constrains the point at its
time through the two equations of (I - d d^T)(x(t) - c) = 0, linear in x(t); a motion
x(t) = sum_k a_k (t - t0)^k is then a linear least-squares fit to the rays (`fit_motion`), and
views from different cameras fix the depth that one view leaves open.

`find_blobs` labels each view's unexplained pixels (the render misses the target by more than
`residual` in some channel, on the target's foreground) into connected blobs. `fit_tracks`
follows blobs through the views in time order: a straight-line motion fitted to a blob and
blobs of compatible colour in the nearest views (every combination of them) is kept when it
reprojects within `gate_px` onto blobs in enough nearby views; the best-supported one is grown
view by view in both directions, each next view's blob taken where the motion fitted to the
track's last blobs predicts it (the object may be hidden for up to `max_gap` of time), and its
blobs are removed before the next track is sought. A track is a list of (time, point, velocity)
from local straight-line fits around each of its blobs (`Track.at` interpolates between them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nehad.carve import _chroma, unexplained_mask


@dataclass(frozen=True)
class Blob:
    """One connected region of unexplained pixels in one view."""

    view: int
    time: float
    centre: np.ndarray  # (2,) its centroid (u, v), in the coordinates Camera.project returns
    area: int  # pixels
    colour: np.ndarray  # (3,) the target's mean rgb over it
    origin: np.ndarray  # (3,) the camera centre
    direction: np.ndarray  # (3,) unit ray through the centroid
    shape: np.ndarray | None = None  # (2, 2) covariance of its pixels' (u, v), pixels^2 (each
    # pixel a unit square); None: round
    cover: float = float("nan")  # the render's mean alpha over its pixels, where `find_blobs`
    # had the renders' alphas: near 0 where nothing is drawn there, near 1 where something is
    # drawn in the wrong colour


def find_blobs(cameras, times, targets, alphas, renders, *, residual: float = 0.25,
               min_area: int = 3, max_area_fraction: float = 0.05,
               close_px: int = 0, covers=None, widen_tol: float = 0.0) -> list[Blob]:
    """The blobs of every view: 8-connected regions of `nehad.carve.unexplained_mask` of at
    least `min_area` pixels and at most `max_area_fraction` of the image (a larger region is
    a badly drawn backdrop, not a missing object). `close_px` > 1: the mask is first closed
    with a disc that many pixels wide, so that an object whose texture has the backdrop's
    colour (the stress suite's striped box: white stripes before a white floor) is one blob,
    not one per stripe of its other colour. `covers`: the renders' alphas (H, W), each blob's
    mean over its pixels kept as its `cover`. `widen_tol` > 0: each blob's centroid, shape and
    colour are taken over the blob widened to the target's foreground pixels of its
    chromaticity (within `widen_tol`) connected to it, near it (`widened`): where the render
    draws part of an object, the unexplained blob is only the rest of it and its centroid is
    off the object's centre (a fast ball variant's, 2.3-3.3 px where its radius was 3.7-6.1;
    docs/results.md, 2026-12-02); its area and cover stay the unexplained pixels'."""
    import cv2

    disc = (cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close_px, close_px))
            if close_px > 1 else None)
    blobs = []
    covers = [None] * len(renders) if covers is None else covers
    for k, (cam, t, target, alpha, drawn, drawn_alpha) in enumerate(
            zip(cameras, times, targets, alphas, renders, covers)):
        bad = unexplained_mask(drawn, target, alpha, residual).astype(np.uint8)
        if disc is not None:
            bad = cv2.morphologyEx(bad, cv2.MORPH_CLOSE, disc)
        n, labels, stats, centres = cv2.connectedComponentsWithStats(bad, connectivity=8)
        most = max_area_fraction * bad.size
        c2w = cam.camera_to_world
        for i in range(1, n):
            area = int(stats[i, cv2.CC_STAT_AREA])
            if area < min_area or area > most:
                continue
            rows, cols = np.nonzero(labels == i)
            cover = float("nan") if drawn_alpha is None else float(drawn_alpha[rows, cols].mean())
            u, v = centres[i] + 0.5  # pixel i spans [i, i + 1) (docs/design.md section 3)
            if widen_tol > 0:
                rows, cols = widened(rows, cols, target, alpha, widen_tol)
                u, v = cols.mean() + 0.5, rows.mean() + 0.5
            d = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]) @ c2w[:3, :3].T
            shape = np.cov(np.stack([cols, rows]).astype(np.float64), bias=True) + np.eye(2) / 12
            blobs.append(Blob(k, float(t), np.array([u, v]), area,
                              target[rows, cols].reshape(-1, 3).mean(axis=0),
                              c2w[:3, 3].copy(), d / np.linalg.norm(d), shape, cover))
    return blobs


#: `widened` looks for an object's pixels this many times the blob's own radius (plus 2 px)
#: from its centroid.
WIDEN_REACH = 3.0


def widened(rows: np.ndarray, cols: np.ndarray, target: np.ndarray, alpha, tol: float):
    """(rows, cols) of a blob's pixels and of the target's pixels around it that continue it:
    foreground (alpha >= 0.5 where known) pixels whose chromaticity is within `tol` of the
    blob's mean, 8-connected to the blob, inside a square of WIDEN_REACH times the blob's
    radius (plus 2 px) about its centroid (so that a backdrop of a like colour does not
    swallow it). A blob whose chromaticity is within 2 `tol` of grey's (1/3 each) is returned
    as it is: pixels within `tol` of grey (white, grey and black floors, walls and
    backdrops) would be taken as its own, and an object's edge blended with a white floor
    is such a blob (the second occluder variant's sphere: its blobs taken for the floor's,
    their colour with them, and its track broken; docs/results.md, 2026-12-02)."""
    import cv2

    colour = _chroma(target[rows, cols].reshape(-1, 3).mean(axis=0))
    if np.abs(colour - 1.0 / 3.0).max() <= 2.0 * tol:
        return rows, cols
    h, w = target.shape[:2]
    reach = int(np.ceil(WIDEN_REACH * np.sqrt(len(rows) / np.pi) + 2))
    r0, c0 = int(rows.mean()), int(cols.mean())
    y0, y1 = max(r0 - reach, 0), min(r0 + reach + 1, h)
    x0, x1 = max(c0 - reach, 0), min(c0 + reach + 1, w)
    patch = target[y0:y1, x0:x1]
    like = np.abs(_chroma(patch) - colour).max(axis=-1) <= tol
    if alpha is not None:
        like &= alpha.reshape(h, w)[y0:y1, x0:x1] >= 0.5
    inside = (rows >= y0) & (rows < y1) & (cols >= x0) & (cols < x1)
    like[rows[inside] - y0, cols[inside] - x0] = True
    _, labels = cv2.connectedComponents(like.astype(np.uint8), connectivity=8)
    keep = np.unique(labels[rows[inside] - y0, cols[inside] - x0])
    grown_r, grown_c = np.nonzero(np.isin(labels, keep[keep > 0]))
    out = np.unique(np.concatenate([(grown_r + y0) * w + grown_c + x0, rows * w + cols]))
    return out // w, out % w


def fit_motion(blobs, t0: float, degree: int = 1) -> np.ndarray | None:
    """Coefficients (degree + 1, 3) of x(t) = sum_k a_k (t - t0)^k nearest, in least squares,
    to the blobs' rays (module docstring), or None when the rays leave it undetermined (too
    few, or all through one point of view). Solved by its normal equations: with P_i the
    projection off ray i and tau_i = t_i - t0, block (j, k) of the matrix is
    sum_i tau_i^(j+k) P_i and block j of the right side sum_i tau_i^j P_i c_i."""
    m = degree + 1
    a = np.zeros((m, 3, m, 3))
    rhs = np.zeros((m, 3))
    for b in blobs:
        p = np.eye(3) - np.outer(b.direction, b.direction)
        pc = p @ b.origin
        powers = (b.time - t0) ** np.arange(2 * m - 1)
        for j in range(m):
            rhs[j] += powers[j] * pc
            for k in range(m):
                a[j, :, k, :] += powers[j + k] * p
    a = a.reshape(3 * m, 3 * m)
    eig = np.linalg.eigvalsh(a)
    if eig[0] <= 1e-9 * max(eig[-1], 1e-300):
        return None
    return np.linalg.solve(a, rhs.reshape(-1)).reshape(m, 3)


def motion_at(coef: np.ndarray, t0: float, t) -> np.ndarray:
    """x(t) of `fit_motion`'s coefficients, (3,) or (T, 3) for an array of times."""
    powers = (np.asarray(t, np.float64)[..., None] - t0) ** np.arange(len(coef))
    return powers @ coef


def _reprojection(cameras, coef, t0: float, blob: Blob) -> float:
    """Pixels between the blob's centroid and the motion's point at the blob's time."""
    cam = cameras[blob.view]
    w2c = cam.world_to_camera
    x = w2c[:3, :3] @ motion_at(coef, t0, blob.time) + w2c[:3, 3]
    if x[2] <= 1e-6:
        return np.inf
    du = cam.fx * x[0] / x[2] + cam.cx - blob.centre[0]
    dv = cam.fy * x[1] / x[2] + cam.cy - blob.centre[1]
    return float(np.hypot(du, dv))


@dataclass
class Track:
    """An object's path through the views: its blobs and, at each blob's time, the point and
    velocity of a straight-line motion fitted to the track's blobs around it."""

    blobs: list
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    velocities: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    end_accelerations: np.ndarray | None = None  # (2, 3): the first and the last sample's
    # (their quadratic fits'), which `smooth_at` runs on with past the ends; None: none

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points (T, 3), velocities (T, 3)) at times t: linearly interpolated between the
        track's samples inside its span, along the end samples' velocities outside it."""
        t = np.asarray(t, np.float64)
        inside = np.clip(t, self.times[0], self.times[-1])
        pts = np.stack([np.interp(inside, self.times, self.points[:, i]) for i in range(3)], 1)
        vel = np.stack([np.interp(inside, self.times, self.velocities[:, i])
                        for i in range(3)], 1)
        return pts + vel * (t - inside)[:, None], vel

    def smooth_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As `at`, but between two samples a cubic through both samples' points with both
        their velocities (Hermite) instead of the chord: across a held-out stretch of several
        frames a turning path keeps its curve (nehad.carry; the chains keep `at`). Past the
        ends, with `end_accelerations`, along the end sample's acceleration as well as its
        velocity: a ball thrown along a parabola lands where it does, not on the tangent."""
        t = np.asarray(t, np.float64)
        pts, vel = self.at(t)
        T, P, V = self.times, self.points, self.velocities
        if len(T) < 2:
            return pts, vel
        i = np.clip(np.searchsorted(T, t) - 1, 0, len(T) - 2)
        inside = (t >= T[0]) & (t <= T[-1])
        h = (T[i + 1] - T[i])[:, None]
        s = ((t - T[i])[:, None] / np.maximum(h, 1e-12))
        p0, p1, v0, v1 = P[i], P[i + 1], V[i] * h, V[i + 1] * h
        cubic = ((2 * s**3 - 3 * s**2 + 1) * p0 + (s**3 - 2 * s**2 + s) * v0
                 + (-2 * s**3 + 3 * s**2) * p1 + (s**3 - s**2) * v1)
        slope = ((6 * s**2 - 6 * s) * p0 + (3 * s**2 - 4 * s + 1) * v0
                 + (-6 * s**2 + 6 * s) * p1 + (3 * s**2 - 2 * s) * v1) / np.maximum(h, 1e-12)
        if self.end_accelerations is not None:  # past the ends: their accelerations too
            acc = self.end_accelerations[(t > T[-1]).astype(np.int64)]
            dt = np.where(inside, 0.0, t - np.where(t < T[0], T[0], T[-1]))[:, None]
            pts, vel = pts + 0.5 * acc * dt**2, vel + acc * dt
        return (np.where(inside[:, None], cubic, pts), np.where(inside[:, None], slope, vel))

    def colour(self) -> np.ndarray:
        return np.average([b.colour for b in self.blobs], axis=0,
                          weights=[b.area for b in self.blobs])


@dataclass(frozen=True)
class TrackSettings:
    """The tracker's tolerances (`fit_tracks`)."""

    gate_px: float = 3.0  # largest reprojection error of a track's blob, in pixels (plus
    # half the blob's own radius)
    colour_tol: float = 0.08  # largest chromaticity difference between blobs of one object
    neighbours: int = 4  # views on each side (in time) a hypothesis is fitted and scored on
    min_support: int = 5  # views a hypothesis must land on to be grown into a track
    min_blobs: int = 6  # blobs a grown track must have to be kept
    max_gap: float = 0.08  # the longest time without a blob (hidden, out of frame) a track
    # is followed through
    fit_blobs: int = 6  # the track's last blobs the prediction of the next view is fitted to
    max_tracks: int = 32  # the recipe passes carve.max_tracks (the same default)
    samples: int = 30  # random draws per anchor blob
    join_blobs: int = 5  # blobs from each end two tracks are joined on (`_join`)
    curved: bool = True  # where no straight hypothesis finds min_support blobs, a quadratic
    # one through five blobs that lands on more (`_curved_hypothesis`)
    refit: bool = True  # where the prediction misses, the next view's blob that one motion
    # fitted to it and the track's last blobs lands within the gates (`_refitted_match`)
    grow_degree: int = 2  # the motion that predicts a track's next blob (`_grow`): 2 a
    # quadratic through the last `fit_blobs` (a straight line over an arc cuts its corner and
    # missed the next blob after a held-out stretch: docs/results.md, 2026-11-27), 1 a line


def _gate(s: TrackSettings, blob: Blob) -> float:
    return s.gate_px + 0.5 * np.sqrt(blob.area / np.pi)


def _compatible(a: Blob, b: Blob, tol: float) -> bool:
    return float(np.abs(_chroma(a.colour) - _chroma(b.colour)).max()) <= tol


class _Views:
    """The blobs grouped by view, the views in time order."""

    def __init__(self, blobs):
        self.order = sorted({(b.time, b.view) for b in blobs})
        self.rank = {v: i for i, (_, v) in enumerate(self.order)}
        self.of = {v: [] for _, v in self.order}
        for b in blobs:
            self.of[b.view].append(b)

    def near(self, view: int, n: int) -> list[int]:
        """The views up to n ranks before and after `view`, nearest first."""
        r = self.rank[view]
        out = []
        for d in range(1, n + 1):
            for q in (r - d, r + d):
                if 0 <= q < len(self.order):
                    out.append(self.order[q][1])
        return out


def _best_match(cameras, coef, t0, candidates, s: TrackSettings):
    """The candidate blob nearest to the motion's point at its time, within its gate."""
    best, best_d = None, np.inf
    for b in candidates:
        d = _reprojection(cameras, coef, t0, b)
        if d <= _gate(s, b) and d < best_d:
            best, best_d = b, d
    return best


def _hypothesis(cameras, views: _Views, anchor: Blob, free, s: TrackSettings,
                rng: np.random.Generator, curve_rng: np.random.Generator | None = None):
    """The best-supported straight-line motion through `anchor` and compatible free blobs of
    three of its neighbouring views (`samples` random draws): the blobs it lands on, or
    None; where it lands on fewer than `min_support`, a curved one if one holds
    (`_curved_hypothesis`, drawn with `curve_rng`)."""
    near = views.near(anchor.view, s.neighbours)
    options = [[b for b in views.of[v] if id(b) in free and _compatible(anchor, b, s.colour_tol)]
               for v in near]
    options = [o for o in options if o]
    if len(options) < 3:
        return None
    best = None
    for _ in range(s.samples):
        support = _drawn_support(cameras, views, anchor, near, options, free, s, rng, 1)
        if support is None:
            continue
        if best is None or len(support) > len(best):
            best = support
            if len(best) == len(near) + 1:
                break
    if (s.curved and curve_rng is not None and (best is None or len(best) < s.min_support)
            and len(options) >= 4):  # its own draws: the straight hypotheses' stay as they were
        curved = _curved_hypothesis(cameras, views, anchor, near, options, free, s, curve_rng)
        if curved is not None:
            return curved
    return best


def _curved_hypothesis(cameras, views: _Views, anchor: Blob, near: list, options: list, free,
                       s: TrackSettings, rng: np.random.Generator):
    """Where no straight line through `anchor` finds `min_support` blobs: the best-supported
    quadratic motion through it and blobs of four of its neighbouring views, kept when it
    lands on two blobs more than it was fitted to (and at least `min_support` + 1) and on
    every neighbouring view with a blob of its colour, or None: nine numbers fit five rays,
    and among blobs with no common path (a sphere that jumps about, at every view) a looser
    rule (one such view missed) made tracks of 6-7 blobs over a fifth of the time. A fast
    object seen in few views, across a held-out stretch, curves between two short runs of
    blobs that no line joins (a variant of the stress suite's fast ball: 4 and 3 blobs, 0.06
    of time apart, docs/results.md, 2026-11-30)."""
    best = None
    for _ in range(s.samples):
        support = _drawn_support(cameras, views, anchor, near, options, free, s, rng, 2)
        if support is None:
            continue
        if (len(support) > max(5 + 1, s.min_support)  # 5: the blobs it was fitted to
                and len(support) > len(options)  # every neighbour with a blob of its colour
                and (best is None or len(support) > len(best))):
            best = support
            if len(best) == len(near) + 1:
                break
    return best


def _drawn_support(cameras, views: _Views, anchor: Blob, near: list, options: list, free,
                   s: TrackSettings, rng: np.random.Generator, degree: int):
    """One random hypothesis of a motion of `degree` (1: a line through the anchor and blobs
    of 3 neighbouring views, 2: a quadratic through it and 4): the blobs of the `near` views
    it lands on (the anchor first), or None when it misses its own sample by more than
    `gate_px`."""
    chosen = rng.choice(len(options), 3 if degree == 1 else 4, replace=False)
    sample = [anchor, *(options[i][rng.integers(len(options[i]))] for i in chosen)]
    coef = fit_motion(sample, anchor.time, degree=degree)
    if coef is None or max(_reprojection(cameras, coef, anchor.time, b)
                           for b in sample) > s.gate_px:
        return None
    support = [anchor]
    for v in near:
        m = _best_match(cameras, coef, anchor.time, [b for b in views.of[v] if id(b) in free], s)
        if m is not None:
            support.append(m)
    return support


def _grow(cameras, views: _Views, blobs: list, free, s: TrackSettings, step: int) -> list:
    """Follow the track `blobs` view by view in time order (`step` +1 forward, -1 back): the
    next view's blob is the one nearest the motion (of `grow_degree`) fitted to the last
    `fit_blobs`, within its gate."""
    blobs = sorted(blobs, key=lambda b: b.time)
    end = blobs[-1] if step > 0 else blobs[0]
    r = views.rank[end.view] + step
    while 0 <= r < len(views.order):
        t, v = views.order[r]
        last = blobs[-1] if step > 0 else blobs[0]
        if abs(t - last.time) > s.max_gap:
            break
        recent = blobs[-s.fit_blobs:] if step > 0 else blobs[:s.fit_blobs]
        coef = None  # a quadratic needs five blobs to be fitted with some to spare
        if s.grow_degree >= 2 and len(recent) >= 5:
            coef = fit_motion(recent, last.time, degree=s.grow_degree)
        if coef is None:
            coef = fit_motion(recent, last.time)
        if coef is None:
            break
        candidates = [b for b in views.of[v] if id(b) in free]
        m = _best_match(cameras, coef, last.time, candidates, s)
        if m is None and s.refit:
            m = _refitted_match(cameras, recent, last, candidates, s)
        if m is not None and _compatible(m, last, s.colour_tol):
            free.discard(id(m))
            blobs = blobs + [m] if step > 0 else [m] + blobs
        r += step
    return blobs


def _refitted_match(cameras, recent: list, last: Blob, candidates: list, s: TrackSettings):
    """The candidate blob that, added to the track's `recent` blobs, leaves every one of them
    within its gate of one motion of `grow_degree` fitted to them all (of several, the one
    whose worst blob is furthest inside its gate), or None. `_grow`'s prediction extrapolates
    a quadratic fitted to a few blobs from different cameras over a short time, whose
    acceleration they barely fix: past two views where the wall's end hid the stress occluder
    variant's sphere it missed the next blobs by 10-28 pixels, where one quadratic through
    the twelve blobs of 0.84-0.95 lands on each within its gate (0.1-2.1 pixels;
    docs/results.md, 2026-11-30)."""
    if len(recent) < 5:
        return None
    best, best_err = None, np.inf
    for b in candidates:
        if not _compatible(b, last, s.colour_tol):
            continue
        both = recent + [b]
        coef = fit_motion(both, last.time, degree=s.grow_degree)
        if coef is None:
            continue
        errs = [_reprojection(cameras, coef, last.time, o) - _gate(s, o) for o in both]
        if max(errs) <= 0.0 and max(errs) < best_err:
            best, best_err = b, max(errs)
    return best


def _samples(cameras, track: Track, s: TrackSettings) -> Track:
    """The track's point and velocity at each blob's time (a quadratic motion fitted to the
    `fit_blobs` + 1 blobs nearest in time, a straight line where they leave it undetermined:
    a straight line over an arc cuts its corner); blobs that land outside their gate are
    dropped."""
    times, points, vels, accs, kept = [], [], [], [], []
    blobs = track.blobs
    for b in blobs:
        near = sorted(blobs, key=lambda o: abs(o.time - b.time))[:s.fit_blobs + 1]
        coef = fit_motion(near, b.time, degree=2) if len(near) >= 5 else None
        if coef is None:
            coef = fit_motion(near, b.time)
        if coef is None or _reprojection(cameras, coef, b.time, b) > _gate(s, b):
            continue
        times.append(b.time)
        points.append(coef[0])
        vels.append(coef[1])
        accs.append(2.0 * coef[2] if len(coef) > 2 else np.zeros(3))
        kept.append(b)
    ends = np.stack([accs[0], accs[-1]]) if kept else None
    return Track(kept, np.array(times), np.array(points).reshape(-1, 3),
                 np.array(vels).reshape(-1, 3), ends)


def completed(tracks: list, wholes: list, cameras, s: TrackSettings) -> list:
    """The `tracks` with the blobs of the whole track they are part of (`wholes`: the tracks of
    the same views with every moving Gaussian transparent, `nehad.spin_tracks.moving_tracks`)
    in the views where they have none; the tracks part of one whole track become one.

    A track of what a model does not draw has a hole, or ends, where the model's field does
    draw the object; with every moving Gaussian hidden, the object is unexplained in every view
    that sees it. An occluder variant's sphere: two tracks over 0.00-0.45 and 0.67-0.95, the
    field drawing it over 0.50-0.61 (training views) with Gaussians it parks inside the
    occluder at every other time; its whole track, 74 blobs over 0.00-0.95 (docs/results.md,
    2026-12-02 afternoon). A track is part of a whole one when half of its blobs or more are
    that one's blobs of their view, within its gate and its colour."""
    parts: dict[int, list] = {}
    out = []
    for track in tracks:
        whole = _containing(track, wholes, s)
        if whole is None:
            out.append(track)
        else:
            parts.setdefault(whole, []).append(track)
    for whole, pieces in parts.items():
        blobs = [b for piece in pieces for b in piece.blobs]
        seen = {b.view for b in blobs}
        blobs += [b for b in wholes[whole].blobs if b.view not in seen]
        out.append(_samples(cameras, Track(sorted(blobs, key=lambda o: o.time)), s))
    return out


def _containing(track: Track, wholes: list, s: TrackSettings) -> int | None:
    """The index of the whole track that half of `track`'s blobs or more lie on (`completed`),
    the one with most; None when none does."""
    best, most = None, 0
    for i, whole in enumerate(wholes):
        of_view = {b.view: b for b in whole.blobs}
        on = sum(1 for b in track.blobs if (o := of_view.get(b.view)) is not None
                 and float(np.linalg.norm(b.centre - o.centre)) <= _gate(s, o)
                 and _compatible(b, o, s.colour_tol))
        if on > most:
            best, most = i, on
    return best if 2 * most >= len(track.blobs) > 0 else None


def _join(cameras, tracks: list, s: TrackSettings) -> list:
    """Join tracks that are one object seen across a stretch of time with no view (a gap in
    the training times) or where it was hidden: a track that ends within `max_gap` of another's
    start (or overlaps it by less) is joined to it when a quadratic motion through the
    `join_blobs` blobs at each side lands on all of them (within their gates) and their
    colours agree."""
    tracks = sorted(tracks, key=lambda tr: tr.times[0])
    joined = True
    while joined:
        joined = False
        for i, a in enumerate(tracks):
            for j, b in enumerate(tracks):
                gap = b.times[0] - a.times[-1]
                if i == j or not -s.max_gap < gap <= s.max_gap or not _compatible(
                        a.blobs[-1], b.blobs[0], s.colour_tol):
                    continue
                ends = a.blobs[-s.join_blobs:] + b.blobs[:s.join_blobs]
                t0 = 0.5 * (a.times[-1] + b.times[0])
                coef = fit_motion(ends, t0, degree=2)
                if coef is None or any(_reprojection(cameras, coef, t0, o) > _gate(s, o)
                                       for o in ends):
                    continue
                both = sorted(a.blobs + b.blobs, key=lambda o: o.time)
                merged = _samples(cameras, Track(both), s)
                tracks = [tr for k, tr in enumerate(tracks) if k not in (i, j)] + [merged]
                tracks.sort(key=lambda tr: tr.times[0])
                joined = True
                break
            if joined:
                break
    return tracks


def fit_tracks(cameras, blobs, settings: TrackSettings | None = None,
               seed: int = 0) -> list[Track]:
    """The tracks through `blobs` (module docstring), longest first: the anchors' hypotheses
    are drawn once and re-drawn only when a track has taken one of their blobs."""
    import heapq

    s = settings or TrackSettings()
    rng, curve_rng = np.random.default_rng(seed), np.random.default_rng([seed, 1])
    views = _Views(blobs)
    free = {id(b) for b in blobs}
    heap = []  # (-support, anchor index, blobs)
    supported = set()  # blobs a found hypothesis lands on: not drawn again as anchors
    for i in sorted(range(len(blobs)), key=lambda i: -blobs[i].area):
        if id(blobs[i]) in supported:
            continue
        h = _hypothesis(cameras, views, blobs[i], free, s, rng, curve_rng)
        if h is not None and len(h) >= s.min_support:
            heapq.heappush(heap, (-len(h), i, h))
            supported.update(id(b) for b in h)
    tracks = []
    while heap and len(tracks) < s.max_tracks:
        _, i, h = heapq.heappop(heap)
        if id(blobs[i]) not in free:
            continue
        if any(id(b) not in free for b in h):  # taken by a track since: draw again
            h = _hypothesis(cameras, views, blobs[i], free, s, rng, curve_rng)
            if h is not None and len(h) >= s.min_support:
                heapq.heappush(heap, (-len(h), i, h))
            continue
        for b in h:
            free.discard(id(b))
        grown = _grow(cameras, views, h, free, s, +1)
        grown = _grow(cameras, views, grown, free, s, -1)
        track = _samples(cameras, Track(grown), s)
        if len(track.blobs) >= s.min_blobs:
            tracks.append(track)
    return sorted(_join(cameras, tracks, s), key=lambda tr: -len(tr.blobs))


def seeds_along(track: Track, cameras, spacing: float, lo: float, hi: float,
                width: float = 0.5):
    """Gaussians for a track: one every `spacing` of time over its span (and half a `max_gap`
    of the default settings beyond its ends, inside [lo, hi]), each at the track's point and
    with its velocity at its time. Returns (points, velocities, times, colours, widths,
    shapes): the width is `width` times the object's radius (the blobs' radius in pixels at
    their depth, median); a shape (3, 3) has the seed's axes as columns, each as long as its
    scale (`blob_axes`: the blob nearest in time stretched to the width; round where blobs
    carry no shape)."""
    reach = 0.5 * TrackSettings().max_gap
    start = max(lo, track.times[0] - reach)
    stop = min(hi, track.times[-1] + reach)
    taus = np.arange(start, stop + 1e-9, spacing)
    pts, vel = track.at(taus)
    radii = []
    for b, p in zip(track.blobs, track.points):
        cam = cameras[b.view]
        _, z = cam.project(p[None, :])
        radii.append(np.sqrt(b.area / np.pi) * z[0] / cam.fx)
    size = width * float(np.median(radii))
    n = len(taus)
    blob_times = np.array([b.time for b in track.blobs])
    nearest = np.abs(taus[:, None] - blob_times[None, :]).argmin(axis=1)
    per_blob = np.stack([blob_axes(b, cameras[b.view], size) for b in track.blobs])
    shapes = per_blob[nearest]
    return (pts, vel, taus, np.repeat(track.colour()[None, :], n, axis=0),
            np.full(n, size), shapes)


#: Unit offsets of a seed's members (`cluster_seeds`): the centre and the six axis points.
_MEMBER_OFFSETS = np.vstack([np.zeros(3), np.eye(3), -np.eye(3)])


def cluster_seeds(pts, vel, times, colours, widths, shapes, members: int, spread: float = 0.6):
    """Each seed of `seeds_along` as `members` Gaussians (1 or 7) that move together: the seed's
    centre and, with 7, the six points `spread` of its axes away along them, each with the
    seed's axes halved. One Gaussian per frame spacing draws an object as a round blur as wide
    as its scale; seven smaller ones fill its extent more evenly. The members keep the seed's
    velocity, time and colour, so they form one chain with it (`chains_of`)."""
    if members == 1:
        return pts, vel, times, colours, widths, shapes
    if members != len(_MEMBER_OFFSETS):
        raise ValueError(f"cluster_seeds: members must be 1 or {len(_MEMBER_OFFSETS)}, got "
                         f"{members}")
    k = len(_MEMBER_OFFSETS)
    offsets = spread * np.einsum("nij,kj->nki", shapes, _MEMBER_OFFSETS)  # (n, k, 3)
    vel, times, colours, widths, shapes = (np.repeat(a, k, axis=0) for a in
                                           (vel, times, colours, 0.5 * widths, 0.5 * shapes))
    return (pts[:, None, :] + offsets).reshape(-1, 3), vel, times, colours, widths, shapes


def blob_axes(blob: Blob, cam, size: float) -> np.ndarray:
    """(3, 3) a Gaussian's axes (columns, a right-handed frame in world coordinates, each as
    long as its scale) shaped like the blob: its pixels' principal axes taken into the
    camera's image plane, scaled so that their geometric mean is `size` (a round blob gets
    `size` on every axis, an elongated one the same area drawn long and thin); the third axis
    along the camera's view direction, as short as the shortest (one view cannot tell an
    object's depth extent)."""
    if blob.shape is None:
        return size * np.eye(3)
    to_plane = np.diag([1.0 / cam.fx, 1.0 / cam.fy])  # pixels -> image-plane units at depth 1
    lam, vec = np.linalg.eigh(to_plane @ blob.shape @ to_plane)
    std = np.sqrt(np.maximum(lam, 1e-30))
    mean = np.sqrt(std[0] * std[1])
    axes_cam = np.zeros((3, 3))
    axes_cam[:2, 0] = vec[:, 1] * size * std[1] / mean  # longest first
    axes_cam[:2, 1] = vec[:, 0] * size * std[0] / mean
    axes_cam[2, 2] = size * std[0] / mean
    axes = cam.camera_to_world[:3, :3] @ axes_cam
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return axes


def drawn_already(points: np.ndarray, colours: np.ndarray, reach: np.ndarray, means: np.ndarray,
                  opacities: np.ndarray, rgb: np.ndarray, colour_tol: float,
                  min_opacity: float = 0.3, count: int = 3) -> np.ndarray:
    """(M,) bool: whether the model already has the object a seed stands for, at the seed's
    time: at least `count` of its Gaussians (centres `means`, `opacities`, view-independent
    colours `rgb`, all at that time) with opacity >= `min_opacity` and the seed's chromaticity
    (within `colour_tol`) lie within `reach` of the seed's point. A blob is also left where the
    model draws an object a little off its place (a fast object the field lags behind); a
    chain there would be a second copy of it, pinned, competing with the one the field moves.
    The chain is for what the model does not draw at all (docs/training.md)."""
    out = np.zeros(len(points), bool)
    solid = opacities.reshape(-1) >= min_opacity
    if not solid.any() or not len(points):
        return out
    near_means, near_chroma = means[solid], _chroma(rgb[solid])
    seed_chroma = _chroma(colours)
    for i, (p, r) in enumerate(zip(points, reach)):
        close = np.einsum("ij,ij->i", near_means - p, near_means - p) <= r * r
        if close.sum() < count:
            continue
        alike = np.abs(near_chroma[close] - seed_chroma[i]).max(axis=1) <= colour_tol
        out[i] = int(alike.sum()) >= count
    return out


def chains_of(means: np.ndarray, velocities: np.ndarray, times: np.ndarray, spacing: float,
              reach: np.ndarray) -> np.ndarray:
    """(M,) chain labels 0, 1, ... of Gaussians that tracks passes seeded (`seeds_along`): two
    belong to one chain when their times are at most 1.5 spacings apart and, each moved with
    its velocity to the middle of their two times, their centres lie within the larger of
    their `reach`es (a chain's neighbours are one spacing apart on one path)."""
    m = len(means)
    parent = np.arange(m)

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(m):
        dt = times - times[i]
        near = np.nonzero((np.abs(dt) <= 1.5 * spacing) & (np.arange(m) > i))[0]
        if not len(near):
            continue
        mid = 0.5 * dt[near, None]  # from each Gaussian's time to the middle of the pair's
        a = means[i] + velocities[i] * mid
        b = means[near] - velocities[near] * mid
        close = np.linalg.norm(a - b, axis=1) <= np.maximum(reach[i], reach[near])
        for j in near[close]:
            parent[root(j)] = root(i)
    roots = np.array([root(i) for i in range(m)], dtype=np.int64)
    return np.unique(roots, return_inverse=True)[1].reshape(-1)


__all__ = ["Blob", "Track", "TrackSettings", "blob_axes", "chains_of", "cluster_seeds", "drawn_already",
           "find_blobs", "fit_motion", "fit_tracks", "motion_at", "seeds_along", "widened"]
