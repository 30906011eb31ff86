"""Residual carving: Gaussians where the picture is consistently wrong and no Gaussian is near
(docs/training.md, "Objects that are never created").

3DGS densification clones and splits Gaussians that already sit on an object, so it cannot create
an object no Gaussian reaches. From a random initial cloud (the MuJoCo ``fused.ply``) a small
object, or one that is behind a large occluder from part of the rig, then never gets any: the
random Gaussians that overlap it in one view cover background in the others and are made
transparent before they find it (measured in docs/training.md: 0 Gaussians on the occluded
sphere of the stress suite after the coarse stage, at 100 and at 400 pixels, with 2500 or 20000
initial points).

A carving pass looks at the training views nearest to one time, as space carving does with
silhouettes, but with the residual:

1. render each view with the current model; a pixel is *unexplained* where the render differs from
   the target by more than `residual` in some channel (and, for images with alpha, the target is
   foreground: alpha >= 0.5);
2. cast a ray through each unexplained pixel of each view (on a grid of `stride` pixels) and
   sample it at `depth_samples` depths across the scene box;
3. a sample is *voted for* by every other view in which it projects onto an unexplained pixel
   whose target chromaticity (rgb / (r + g + b): shading divided out, since the lit and the
   shaded side of one object differ in brightness) is within `colour_tol` of the ray's (within
   a motion allowance for views of other times); it is accepted when it is in frame in at least
   `min_views` other views and voted for by `agree` of them, at the depth with the most
   votes along its ray. Points behind a correctly drawn occluder lose the views that see the
   occluder, points off the object land on explained pixels: only the object's own place gathers
   the votes;
4. each accepted point becomes a Gaussian of the target colour, opacity `opacity`, as wide as
   the pixel grid at its depth, with its Boltzmann equilibrium at the pass's time
   (mu_eq = its position, t_eq = that time: the position mask holds it still there, paper Sec.
   "Boltzmann Equilibrium Decomposition"), so it is drawn where it was seen; in a deforming
   stage it also lives only around that time (life rate k = 1 / sigma, nehad.gaussians): at
   other times the object it stands for is elsewhere, and a Gaussian drawn there would be made
   transparent and pruned before the field learns to carry it.

When the Gaussian cap is reached, as many of the least opaque Gaussians are removed first (they
are relocated, as 3DGS-MCMC relocates dead Gaussians), so a full budget cannot starve an object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from nehad.data.synth_gaussians import rotation_to_quat
from nehad.gaussians import rgb_to_sh_dc


def _ray_box(origin: np.ndarray, dirs: np.ndarray, box: np.ndarray):
    """Entry and exit ray parameters of rays origin + s dirs through the box (2, 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
        t1 = (box[0] - origin) * inv
        t2 = (box[1] - origin) * inv
    near = np.minimum(t1, t2).max(axis=1)
    far = np.maximum(t1, t2).min(axis=1)
    return np.maximum(near, 1e-3), far


def _pixel_rays(cam, u: np.ndarray, v: np.ndarray, box: np.ndarray):
    """Rays through the centres of pixels (u, v) of `cam`: (origin (3,), directions (R, 3)
    scaled so that the ray parameter is the depth along the camera z, entry and exit
    parameters through `box`)."""
    c2w = cam.camera_to_world
    dirs = np.stack([(u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy,
                     np.ones(len(u))], 1) @ c2w[:3, :3].T
    origin = c2w[:3, 3]
    near, far = _ray_box(origin, dirs, box)
    return origin, dirs, near, far


def _chroma(rgb: np.ndarray) -> np.ndarray:
    """rgb / (r + g + b): a surface's colour with its shading divided out (a lit and a shaded
    side of one object agree), and 1/3 each for white, grey and black."""
    return rgb / np.maximum(rgb.sum(axis=-1, keepdims=True), 1e-3)


def unexplained_mask(render: np.ndarray, target: np.ndarray, alpha: np.ndarray | None,
                     residual: float) -> np.ndarray:
    """(H, W) bool: the render misses the target by more than `residual` in some channel (and
    the target is foreground where alpha is known)."""
    bad = np.abs(render - target).max(axis=-1) > residual
    if alpha is not None:
        bad &= alpha.reshape(bad.shape) >= 0.5
    return bad


def _match_distances(bad, chromas, centre: np.ndarray, tol: float) -> list[np.ndarray]:
    """Per view: the distance in pixels from each pixel to the nearest unexplained pixel whose
    target chromaticity (`chromas`, per view) is within `tol` of `centre` (inf where there is
    none)."""
    import cv2

    out = []
    for b, c in zip(bad, chromas):
        match = b & (np.abs(c - centre).max(axis=-1) <= tol)
        if not match.any():
            out.append(np.full(b.shape, np.inf, np.float32))
            continue
        out.append(cv2.distanceTransform((~match).astype(np.uint8), cv2.DIST_L2, 3))
    return out


@dataclass(frozen=True)
class _CarvePass:
    """What every view of one carving pass needs (the arguments of `carve_points`)."""

    cameras: list
    targets: list
    bad: list  # per view: (H, W) bool, the unexplained pixels
    box: np.ndarray
    times: np.ndarray
    render_alphas: list | None
    render_depths: list | None
    margin: float  # how far behind a drawn surface a point is hidden by it
    stride: int
    min_views: int
    agree: float
    motion: float
    depth_fractions: np.ndarray  # (S,) where the depth samples sit between entry and exit


def carve_points(cameras, targets, alphas, renders, box: np.ndarray, times=None, *,
                 render_alphas=None, render_depths=None, residual: float = 0.25,
                 stride: int = 2, depth_samples: int = 96, min_views: int = 2,
                 agree: float = 0.6, colour_tol: float = 0.08, motion: float = 1.5,
                 max_rays: int = 3000, rng: np.random.Generator | None = None):
    """The accepted points of one carving pass (module docstring, steps 1-3).

    `cameras`: runtime Cameras; `targets`, `renders`: (H, W, 3) float arrays per view; `alphas`:
    (H, W) or None per view; `box`: (2, 3) scene box to sample depths in; `times`: each view's
    time (None: all the same). An object may move between views of different times: view j's
    vote for a point of view k counts an unexplained pixel of the ray's chromaticity within
    1 + `motion` |t_j - t_k| W pixels of the point's projection (W the image width: `motion` is
    the largest image speed expected, in image widths per unit of time). With the renders'
    alpha and depth, a view in which the point lies behind a drawn, explained surface (by more
    than 2% of the box's diagonal) is occluded there and neither votes nor counts. Returns
    (points (M, 3), colours (M, 3), pixel widths (M,): the world size of `stride` pixels at each
    point) and the number of unexplained grid pixels.
    """
    rng = rng or np.random.default_rng(0)
    margin = 0.02 * float(np.linalg.norm(box[1] - box[0]))
    times = np.zeros(len(cameras)) if times is None else np.asarray(times, np.float64)
    bad = [unexplained_mask(r, t, a, residual) for r, t, a in zip(renders, targets, alphas)]
    rays = _grid_rays(bad, stride)
    n_bad = len(rays)
    empty = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), n_bad
    if not rays or len(cameras) < min_views + 1:
        return empty
    rays = np.asarray(rays)
    if len(rays) > max_rays:
        rays = rays[rng.choice(len(rays), max_rays, replace=False)]
    chromas = [_chroma(t) for t in targets]
    job = _CarvePass(cameras, targets, bad, box, times, render_alphas, render_depths, margin,
                     stride, min_views, agree, motion,
                     (np.arange(depth_samples) + 0.5) / depth_samples)
    found = []
    for centre, in_class in _colour_classes(rays, chromas, colour_tol):
        dist = _match_distances(bad, chromas, centre, colour_tol)
        for k in np.unique(rays[in_class, 0]):
            carved = _carve_view(job, k, rays[in_class & (rays[:, 0] == k)], dist)
            if carved is not None:
                found.append(carved)
    if not found:
        return empty
    pts_out, cols_out, width_out = zip(*found)
    return (np.concatenate(pts_out), np.concatenate(cols_out), np.concatenate(width_out), n_bad)


def _grid_rays(bad, stride: int) -> list[tuple]:
    """(view, v, u) of every unexplained pixel on the `stride` grid of each view."""
    rays = []
    for k, b in enumerate(bad):
        vs, us = np.nonzero(b[::stride, ::stride])
        rays += [(k, v * stride, u * stride) for v, u in zip(vs, us)]
    return rays


def _colour_classes(rays: np.ndarray, chromas, colour_tol: float):
    """One colour class per chromaticity cell of size `colour_tol`: yields (the cell's centre
    chromaticity (3,), which rays are in it (R,) bool); each class gets its distance maps."""
    chroma = np.stack([chromas[k][v, u] for k, v, u in rays])
    keys = np.round(chroma[:, :2] / colour_tol).astype(np.int64)
    for key in np.unique(keys, axis=0):
        in_class = np.all(keys == key, axis=1)
        centre = np.array([key[0] * colour_tol, key[1] * colour_tol,
                           1.0 - (key[0] + key[1]) * colour_tol])
        yield centre, in_class


def _carve_view(job: _CarvePass, k, mine: np.ndarray, dist):
    """The accepted points on the rays `mine` ((R, 3) rows of view, v, u) of view k, against
    the distance maps `dist` of their colour class: (points, colours, pixel widths), or None
    when none is accepted."""
    cam = job.cameras[k]
    v, u = mine[:, 1], mine[:, 2]
    origin, dirs, near, far = _pixel_rays(cam, u, v, job.box)
    hit = far > near
    if not hit.any():
        return None
    v, u, dirs, near, far = v[hit], u[hit], dirs[hit], near[hit], far[hit]
    depth = near[:, None] + (far - near)[:, None] * job.depth_fractions[None, :]  # (R, S)
    pts = origin + depth[..., None] * dirs[:, None, :]  # (R, S, 3)
    votes, seen = _count_votes(job, k, pts.reshape(-1, 3), dist, depth.shape)
    # the most votes; among equals the nearest depth (the first surface)
    best = votes.argmax(axis=1)
    r = np.arange(len(best))
    bv, bs = votes[r, best], seen[r, best]
    take = (bs >= job.min_views) & (bv >= job.agree * np.maximum(bs, 1))
    if not take.any():
        return None
    return (pts[r, best][take], job.targets[k][v[take], u[take]],
            depth[r, best][take] * job.stride / cam.fx)


def _count_votes(job: _CarvePass, k, flat: np.ndarray, dist, shape):
    """(votes, seen), each of `shape`: how many views other than k vote for each sample point
    of `flat` (P, 3), and in how many it is in frame and not hidden."""
    votes = np.zeros(shape, np.int32)
    seen = np.zeros(shape, np.int32)
    for j in range(len(job.cameras)):
        if j == k:
            continue
        inside, ok = _view_votes(job, j, k, flat, dist[j])
        seen += inside.reshape(shape)
        votes += ok.reshape(shape)
    return votes, seen


def _view_votes(job: _CarvePass, j: int, k, flat: np.ndarray, dist_j: np.ndarray):
    """(inside, ok), each (P,) bool: the points `flat` of view k that view j sees (in frame,
    not behind a drawn, explained surface), and those it votes for (an unexplained pixel of
    the class within the motion allowance of their projection)."""
    other = job.cameras[j]
    uv, z = other.project(flat)
    uj = np.floor(uv[:, 0]).astype(np.int64)
    vj = np.floor(uv[:, 1]).astype(np.int64)
    inside = ((z > 1e-3) & (uj >= 0) & (vj >= 0) & (uj < other.width)
              & (vj < other.height))
    idx = np.flatnonzero(inside)
    if job.render_depths is not None:  # behind a drawn surface that is right: hidden
        a_j = job.render_alphas[j][vj[idx], uj[idx]]
        d_j = job.render_depths[j][vj[idx], uj[idx]]
        hidden = (a_j >= 0.5) & ~job.bad[j][vj[idx], uj[idx]] & (d_j < z[idx] - job.margin)
        inside[idx[hidden]] = False
        idx = idx[~hidden]
    slack = 1.0 + job.motion * abs(job.times[j] - job.times[k]) * other.width
    ok = np.zeros(len(flat), bool)
    ok[idx] = dist_j[vj[idx], uj[idx]] <= slack
    return inside, ok


def seed_rays(cameras, targets, alphas, renders, box: np.ndarray, *, residual: float = 0.25,
              stride: int = 2, depth_samples: int = 24, max_rays: int = 400,
              rng: np.random.Generator | None = None):
    """Ray seeding: points at `depth_samples` jittered depths across `box` along the ray of
    every unexplained pixel (on a `stride` grid) of each view, no vote. Where voting needs the
    object in several views at once (a fast object is seen by one camera per time in a MuJoCo
    rig), seeding leaves the choice of depth to the optimisation: each seed lives around its
    view's time, the views of the neighbouring times see the seeds at the wrong depths over
    background and make them transparent, the one on the object stays. Returns (points,
    colours, pixel widths, number of unexplained grid pixels) like `carve_points`."""
    rng = rng or np.random.default_rng(0)
    pts_out, cols_out, width_out, n_bad = [], [], [], 0
    for cam, target, alpha, drawn in zip(cameras, targets, alphas, renders):
        bad = unexplained_mask(drawn, target, alpha, residual)
        vs, us = np.nonzero(bad[::stride, ::stride])
        vs, us = vs * stride, us * stride
        n_bad += len(vs)
        if len(vs) > max_rays:
            pick = rng.choice(len(vs), max_rays, replace=False)
            vs, us = vs[pick], us[pick]
        if not len(vs):
            continue
        origin, dirs, near, far = _pixel_rays(cam, us, vs, box)
        hit = far > near
        vs, us, dirs, near, far = vs[hit], us[hit], dirs[hit], near[hit], far[hit]
        s = (np.arange(depth_samples)[None, :] + rng.random((len(vs), depth_samples))) \
            / depth_samples
        depth = near[:, None] + (far - near)[:, None] * s
        pts_out.append((origin + depth[..., None] * dirs[:, None, :]).reshape(-1, 3))
        cols_out.append(np.repeat(target[vs, us], depth_samples, axis=0))
        width_out.append((depth * stride / cam.fx).reshape(-1))
    if not pts_out:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), n_bad
    return (np.concatenate(pts_out), np.concatenate(cols_out), np.concatenate(width_out), n_bad)


def new_gaussians(points: np.ndarray, colours: np.ndarray, widths: np.ndarray, t_eq,
                  like, opacity: float, life_sigma: float = 0.0,
                  free_offset: float = 0.0, velocities: np.ndarray | None = None,
                  shapes: np.ndarray | None = None) -> dict:
    """Parameter tensors (a dict per GaussianParameters.NAMES) for Gaussians at `points`, living
    around `t_eq` (one time, or one per point) with a temporal standard deviation `life_sigma`
    (0: at every time), moving with `velocities` (M, 3) over their life (None: still). Their
    equilibrium mu_eq is their position, or, with `free_offset` > 0, that far from it along +x
    (out of the position mask's reach: the field moves them from the start). `shapes` (M, 3, 3)
    gives each its axes as columns of a right-handed frame, each as long as its scale (None:
    round, `widths`)."""
    n = len(points)
    t_eq = np.broadcast_to(np.asarray(t_eq, np.float64), (n,))
    velocities = np.zeros((n, 3)) if velocities is None else velocities
    f32 = lambda a: torch.tensor(np.asarray(a, np.float32))  # a copy (t_eq is a broadcast view)
    means = f32(points)
    sh_rest = torch.zeros((n,) + tuple(like.sh_rest.shape[1:]))
    sh_dc = torch.zeros((n,) + tuple(like.sh_dc.shape[1:]))
    sh_dc[:, 0, :] = rgb_to_sh_dc(f32(colours))
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    log_scales = torch.log(f32(widths)).reshape(n, 1).repeat(1, 3)
    if shapes is not None and n:
        scales = np.linalg.norm(shapes, axis=1)  # (M, 3): each column's length
        rot = shapes / scales[:, None, :]
        quats, log_scales = f32(rotation_to_quat(rot)), torch.log(f32(scales))
    return {"means": means, "log_scales": log_scales,
            "quats": quats,
            "opacity_logits": torch.full((n,) + tuple(like.opacity_logits.shape[1:]),
                                         math.log(opacity / (1.0 - opacity))),
            "sh_dc": sh_dc, "sh_rest": sh_rest,
            "mu_eq": means + torch.tensor([float(free_offset), 0.0, 0.0]),
            "t_eq": f32(t_eq).reshape((n,) + tuple(like.t_eq.shape[1:])),
            "life_rate": torch.full((n,) + tuple(like.life_rate.shape[1:]),
                                    1.0 / life_sigma if life_sigma > 0 else 0.0),
            "velocity": f32(velocities).reshape((n,) + tuple(like.velocity.shape[1:]))}


__all__ = ["carve_points", "new_gaussians", "seed_rays", "unexplained_mask"]
