"""Gaussian trajectories (the paper's trajectory figure): the centres of a sample of Gaussians
tracked over time, projected through a camera and drawn as coloured paths over a render.

Works on any source of deformed Gaussians: a function ``gaussians_at(t) -> GaussianCloud``, such
as ``OnnxModel(path).gaussians`` (no torch) or ``lambda t: cloud_at(model, t, degree)`` for a
training run. A track is exactly the sequence of the Gaussian's deformed means at the sampled
times; nothing is smoothed or interpolated.

    tracks = compute_tracks(model.gaussians, camera, track_times((0, 1), 32), count=300)
    image = trajectory_image(model.gaussians, camera, tracks, background=(1, 1, 1))
    write_video("traj.mp4", trajectory_frames(model.gaussians, camera, tracks, (1, 1, 1)))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from nehad.runtime.gaussians import GaussianCloud
from nehad.runtime.mp4 import DEFAULT_CRF

from . import VizError
from .plots import PALETTE, colormap, to_uint8

GaussiansAt = Callable[[float], GaussianCloud]

#: Points closer than this to the camera plane are not drawn (the rasterizer's cull, docs/design.md section 6).
NEAR = 0.2
SELECT_MODES = ("moving", "random")
COLOR_MODES = ("time", "track")


@dataclass
class Tracks:
    """K tracked Gaussians at T times.

    times (T,); ids (K,) indices into the cloud; world (T, K, 3) deformed means; pixels (T, K, 2)
    projections (u, v) with pixel centres at +0.5 (docs/design.md section 3); depth (T, K) view depth z;
    path_length (K,) summed world distance between consecutive times."""

    times: np.ndarray
    ids: np.ndarray
    world: np.ndarray
    pixels: np.ndarray
    depth: np.ndarray
    path_length: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def track_times(time_range, count: int) -> np.ndarray:
    """`count` evenly spaced times over [lo, hi] (both ends included)."""
    lo, hi = (float(v) for v in time_range)
    count = int(count)
    if count < 2:
        raise VizError(f"track times: need at least 2 times, got {count}")
    return np.linspace(lo, hi, count)


def _project(camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uv, z = camera.project(points.reshape(-1, 3))
    return uv.reshape(points.shape[:-1] + (2,)), z.reshape(points.shape[:-1])


def all_positions(gaussians_at: GaussiansAt, times) -> tuple[np.ndarray, np.ndarray]:
    """(T, N, 3) deformed means of every Gaussian at `times`, and the opacities (N,) at the
    first time. The Gaussian count must not change with time."""
    world, opac = [], None
    for t in times:
        cloud = gaussians_at(float(t))
        if world and len(cloud) != world[0].shape[0]:
            raise VizError(f"the source has {len(cloud)} Gaussians at t = {t:g} but "
                           f"{world[0].shape[0]} at t = {times[0]:g}")
        world.append(np.asarray(cloud.means, np.float32))
        if opac is None:
            opac = np.asarray(cloud.opacities, np.float32)
    return np.stack(world), opac


def path_lengths(world: np.ndarray) -> np.ndarray:
    """Summed distance between consecutive positions: (T, N, 3) -> (N,)."""
    if world.shape[0] < 2:
        return np.zeros(world.shape[1], np.float64)
    return np.linalg.norm(np.diff(world.astype(np.float64), axis=0), axis=2).sum(0)


def select_gaussians(world: np.ndarray, opacities: np.ndarray, camera, count: int,
                     mode: str = "moving", seed: int = 0, min_opacity: float = 0.1) -> np.ndarray:
    """Indices of up to `count` Gaussians to track, sorted.

    Candidates: opacity >= min_opacity and in front of the camera and inside the image at some
    time. mode "moving": drawn without replacement with probability proportional to the path
    length (movers are favoured, spread over all moving parts; static ones only fill up when
    too few move); "random": uniform over the candidates. Deterministic for a seed."""
    if mode not in SELECT_MODES:
        raise VizError(f"select: unknown mode {mode!r}; expected one of {', '.join(SELECT_MODES)}")
    count = int(count)
    if count < 1:
        raise VizError(f"count: expected at least 1 Gaussian to track, got {count}")
    uv, z = _project(camera, world)
    inside = ((z > NEAR) & (uv[..., 0] >= 0) & (uv[..., 0] < camera.width)
              & (uv[..., 1] >= 0) & (uv[..., 1] < camera.height)).any(0)
    cand = np.flatnonzero(inside & (np.asarray(opacities) >= min_opacity))
    if cand.size == 0:
        raise VizError(f"no Gaussian with opacity >= {min_opacity:g} is in view of the camera")
    rng = np.random.default_rng(seed)
    if cand.size <= count:
        return np.sort(cand)
    if mode == "random":
        return np.sort(rng.choice(cand, count, replace=False))
    length = path_lengths(world[:, cand])
    moving = length > 1e-6 * max(float(length.max()), 1e-30)
    n_moving = int(moving.sum())
    if n_moving >= count:
        p = length[moving] / length[moving].sum()
        chosen = rng.choice(cand[moving], count, replace=False, p=p)
    else:  # all movers, then static ones at random
        rest = rng.choice(cand[~moving], count - n_moving, replace=False)
        chosen = np.concatenate([cand[moving], rest])
    return np.sort(chosen)


def compute_tracks(gaussians_at: GaussiansAt, camera, times, count: int = 300,
                   mode: str = "moving", seed: int = 0, min_opacity: float = 0.1,
                   ids=None) -> Tracks:
    """Track a sample of Gaussians (or the given `ids`) through `times` (see `select_gaussians`)."""
    times = np.asarray(times, np.float64).reshape(-1)
    if times.size < 2:
        raise VizError(f"track times: need at least 2 times, got {times.size}")
    world, opac = all_positions(gaussians_at, times)
    if ids is None:
        ids = select_gaussians(world, opac, camera, count, mode, seed, min_opacity)
    else:
        ids = np.asarray(ids, np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= world.shape[1]):
            raise VizError(f"ids: indices must be in 0..{world.shape[1] - 1}")
    sel = world[:, ids]
    uv, z = _project(camera, sel)
    return Tracks(times, ids, sel, uv, z, path_lengths(sel))


def _track_colors(tracks: Tracks, color_by: str) -> np.ndarray:
    """(T-1, K, 3) uint8 RGB colour of each segment."""
    t, k = tracks.times.size, len(tracks)
    if color_by == "time":
        span = tracks.times[-1] - tracks.times[0]
        mid = 0.5 * (tracks.times[1:] + tracks.times[:-1])
        f = (mid - tracks.times[0]) / span if span > 0 else np.zeros(t - 1)
        # turbo without its darkest ends, so early and late segments stay visible
        c = np.round(colormap(0.06 + 0.88 * f, "turbo") * 255).astype(np.uint8)
        return np.broadcast_to(c[:, None, :], (t - 1, k, 3))
    if color_by == "track":
        pal = np.array(PALETTE, np.uint8)
        c = pal[np.arange(k) % len(pal)]
        return np.broadcast_to(c[None], (t - 1, k, 3))
    raise VizError(f"color: unknown mode {color_by!r}; expected one of {', '.join(COLOR_MODES)}")


def draw_tracks(image, tracks: Tracks, upto: int | None = None, trail: int | None = None,
                color_by: str = "time", thickness: int | None = None,
                heads: bool = True) -> np.ndarray:
    """Draw the tracks over `image` (RGB, float [0, 1] or uint8) and return a uint8 copy.

    Segments between times k and k+1 for k < upto (all when None), only the last `trail`
    segments when given; a dot at each track's position at time index `upto` (the last time when
    None). Points behind the camera (z <= NEAR) break a track."""
    import cv2

    img = np.ascontiguousarray(to_uint8(image)[..., :3]).copy()
    h, w = img.shape[:2]
    t = tracks.times.size
    last = t - 1 if upto is None else int(min(max(upto, 0), t - 1))
    first = 0 if trail is None else max(0, last - int(trail))
    if thickness is None:
        thickness = max(1, int(round(min(h, w) / 400)))
    colors = _track_colors(tracks, color_by)
    shift = 4
    s = 1 << shift
    pix = np.clip(np.nan_to_num(tracks.pixels, nan=-1e6), -1e6, 1e6)
    fixed = np.round(pix * s).astype(np.int64)
    ok = np.isfinite(tracks.pixels).all(-1) & (tracks.depth > NEAR)
    for k in range(first, last):
        good = ok[k] & ok[k + 1]
        for j in np.flatnonzero(good):
            c = tuple(int(v) for v in colors[k, j])
            cv2.line(img, (int(fixed[k, j, 0]), int(fixed[k, j, 1])),
                     (int(fixed[k + 1, j, 0]), int(fixed[k + 1, j, 1])), c, thickness,
                     cv2.LINE_AA, shift)
    if heads:  # a small dot with a grey rim at each current position
        r = int(round((0.5 * thickness + 0.7) * s))
        ci = max(last - 1, 0)
        for j in np.flatnonzero(ok[last]):
            c = tuple(int(v) for v in colors[ci, j]) if t > 1 else (0, 0, 0)
            centre = (int(fixed[last, j, 0]), int(fixed[last, j, 1]))
            cv2.circle(img, centre, r + s // 3, (70, 70, 70), -1, cv2.LINE_AA, shift)
            cv2.circle(img, centre, r, c, -1, cv2.LINE_AA, shift)
    return img


def _dimmed(rgb: np.ndarray, dim: float) -> np.ndarray:
    """Blend a render towards white so that coloured paths stand out."""
    return (1.0 - dim) * np.asarray(rgb, np.float32) + dim


def render_rgb(gaussians_at: GaussiansAt, camera, t: float, background) -> np.ndarray:
    from nehad.runtime.raster import render

    return render(gaussians_at(float(t)), camera, background=tuple(background)).rgb


def trajectory_image(gaussians_at: GaussiansAt, camera, tracks: Tracks, background=(1, 1, 1),
                     base_time: float | None = None, dim: float = 0.45,
                     color_by: str = "time") -> np.ndarray:
    """The tracks drawn over a render at `base_time` (default the first tracked time), the render
    blended `dim` of the way to white. uint8 RGB."""
    t0 = float(tracks.times[0] if base_time is None else base_time)
    base = _dimmed(render_rgb(gaussians_at, camera, t0, background), dim)
    return draw_tracks(base, tracks, color_by=color_by)


def trajectory_frames(gaussians_at: GaussiansAt, camera, tracks: Tracks, background=(1, 1, 1),
                      trail: int | None = None, dim: float = 0.25,
                      color_by: str = "time") -> Iterable[np.ndarray]:
    """One uint8 frame per tracked time: the render at that time with the paths so far (the last
    `trail` segments when given) and the Gaussians' current positions."""
    for k, t in enumerate(tracks.times):
        base = _dimmed(render_rgb(gaussians_at, camera, float(t), background), dim)
        yield draw_tracks(base, tracks, upto=k, trail=trail, color_by=color_by)


def write_video(path, frames: Iterable[np.ndarray], fps: float = 24.0,
                crf: int = DEFAULT_CRF) -> int:
    """Encode RGB frames (uint8 or float [0, 1]) as an .mp4 through :mod:`nehad.runtime.mp4`
    (H.264 yuv420p through PyAV, OpenCV mp4v without it; atomically; odd sizes padded by
    repeating the last row/column). Returns the number of frames written; problems with the
    input raise VizError naming the file."""
    from nehad.runtime.mp4 import Mp4Writer

    with Mp4Writer(path, fps, crf, error=VizError) as video:
        for frame in frames:
            video.write(frame)
    return video.frames


__all__ = ["COLOR_MODES", "NEAR", "SELECT_MODES", "Tracks", "all_positions", "compute_tracks",
           "draw_tracks", "path_lengths", "render_rgb", "select_gaussians", "track_times",
           "trajectory_frames", "trajectory_image", "write_video"]
