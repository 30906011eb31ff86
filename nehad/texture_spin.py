"""A round object's spin, from its texture (docs/training.md, "Objects that spin").

A round body's outline does not turn with it, so its blobs' shapes say nothing of its spin
(`nehad.spin` reports none for the stress suite's checkered sphere); its texture does. Each
training view that sees the body shows part of its surface: a pixel's ray meets the body, taken
as a ball about the tracked point, at a direction d from its centre, and the body turning at w
had that point of its surface at direction R(t - t_c)^T d at time t_c. At the right w, the
pixels of every view that land on one patch of the body's surface at t_c have one colour; at a
wrong one, the patterns of views at different times are laid over each other turned apart and
every patch mixes colours. So w is the one that makes the patches' colours agree: the spread
of colour within patches of a grid over the ball (`texture_misfit`), searched over directions
and rates on a window of time about the track's middle and refined on ever wider windows, as
`nehad.spin` does with the shapes.

Colours are taken as chromaticity (r, g, b over their sum): the body's shading by a light fixed
in the world changes with d, not with the body's turn, and would otherwise mix each patch of a
turning body's surface by itself. On the stress suite's checkered sphere (its true path and
radius; 84 training views at 200x200) the search finds 18.86 rad per unit of time (truth
18.85) about an axis 0.2 degrees from the true one, with 0.23 of no spin's misfit; along the
true axis the minimum's basin is about 1.5 rad per unit of time wide either side (docs/results.md,
2026-12-03).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from nehad.spin import Spin, sphere_directions

#: Patches of the ball: the cells of a grid of this many a side over the cube about it that
#: its surface crosses; coarse for the search, whose grid must land in the minimum's basin,
#: finer for the refinement.
SEARCH_PATCHES = 6
REFINE_PATCHES = 12

#: The search's window of time either side of the track's middle, and the wider ones the spin
#: is refined on in turn (a rate off by dw turns the body dw (t - t_c) from its place).
WINDOWS = (0.06, 0.15, 0.3, 0.6, float("inf"))

#: Rates are searched up to this many radians a frame spacing (a checker of 8 cells about the
#: body moves half a cell a frame spacing at 0.4): past it, views a frame apart no longer show
#: one patch of the surface twice.
MAX_TURN_PER_FRAME = 0.5

#: Pixels whose rays meet the ball at less than this cosine of incidence are left out: at its
#: outline a pixel covers much of the surface and the tracked point's error moves it most.
FACING = 0.3

#: At most this many surface samples a view (`surface_samples`, evenly thinned); a window of
#: time with fewer than MIN_SAMPLES is skipped.
SAMPLES_PER_VIEW = 400
MIN_SAMPLES = 50


@dataclass(frozen=True)
class SurfaceSamples:
    """Pixels of the views that see a ball: each one's time (n,), the direction from the
    ball's centre to where its ray meets the ball (n, 3, unit) and its chromaticity (n, 3)."""

    times: np.ndarray
    directions: np.ndarray
    chroma: np.ndarray


def surface_samples(views, centres: np.ndarray, radius: float) -> SurfaceSamples:
    """The samples of `views` ((camera, time, image (H, W, 3)) each) of a ball of `radius` at
    `centres` (one per view): every pixel whose ray meets it facing (`FACING`)."""
    times, dirs, chroma = [], [], []
    for (cam, t, image), centre in zip(views, np.asarray(centres, np.float64)):
        d, rgb = _ball_pixels(cam, np.asarray(image), centre, radius)
        if len(d) > SAMPLES_PER_VIEW:
            keep = np.linspace(0, len(d) - 1, SAMPLES_PER_VIEW).astype(np.int64)
            d, rgb = d[keep], rgb[keep]
        times.append(np.full(len(d), float(t)))
        dirs.append(d)
        chroma.append(rgb / np.maximum(rgb.sum(1, keepdims=True), 1e-6))
    if not times:
        return SurfaceSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    return SurfaceSamples(np.concatenate(times), np.concatenate(dirs), np.concatenate(chroma))


def _ball_pixels(cam, image: np.ndarray, centre: np.ndarray, radius: float):
    """(directions (m, 3), rgb (m, 3)) of the pixels of one view whose rays meet the ball
    facing: each ray's first meeting with the ball, as a unit direction from its centre."""
    (u0, v0), depth = (x[0] for x in cam.project(centre[None]))
    if not depth > radius:
        return np.zeros((0, 3)), np.zeros((0, 3))
    h, w = image.shape[:2]
    reach = 1.2 * cam.fx * radius / (depth - radius)
    us = np.arange(max(0, int(u0 - reach)), min(w, int(u0 + reach) + 1))
    vs = np.arange(max(0, int(v0 - reach)), min(h, int(v0 + reach) + 1))
    if not len(us) or not len(vs):
        return np.zeros((0, 3)), np.zeros((0, 3))
    uu, vv = (a.reshape(-1) for a in np.meshgrid(us, vs))
    rays = np.stack([(uu + 0.5 - cam.cx) / cam.fx, (vv + 0.5 - cam.cy) / cam.fy,
                     np.ones(len(uu))], 1) @ cam.world_to_camera[:3, :3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    to_eye = cam.centre - centre
    b = rays @ to_eye
    disc = b * b - (to_eye @ to_eye - radius * radius)
    hit = disc > 0.0
    along = -b[hit] - np.sqrt(disc[hit])
    d = (to_eye + rays[hit] * along[:, None]) / radius
    facing = -(rays[hit] * d).sum(1) >= FACING
    rgb = image[vv[hit], uu[hit], :3].astype(np.float64)
    return d[facing], rgb[facing]


def texture_misfit(omegas, samples: SurfaceSamples, centre_time: float,
                   patches=REFINE_PATCHES) -> np.ndarray:
    """(c,) for each angular velocity of `omegas` (c, 3): the samples' chromaticity spread
    within the patches of the ball that they fall in once turned back to `centre_time`
    (summed squared deviation from each patch's mean, per sample)."""
    omegas = np.ascontiguousarray(omegas, np.float64).reshape(-1, 3)
    if not len(samples.times):
        return np.zeros(len(omegas))
    return _misfits(omegas, samples.times - centre_time, samples.directions, samples.chroma,
                    int(patches))


@numba.njit(cache=True)
def _misfits(omegas, dts, dirs, chroma, patches):
    """`texture_misfit`'s loop: each sample turned back by -w dt (Rodrigues), its patch (the
    cell of a `patches`-a-side grid over the cube about the ball) found and its colour summed
    there, the patches' spread summed."""
    n, cells = len(dts), patches ** 3
    out = np.empty(len(omegas))
    count = np.empty(cells)
    sums = np.empty((cells, 3))
    squares = np.empty(cells)
    for c in range(len(omegas)):
        wx, wy, wz = omegas[c, 0], omegas[c, 1], omegas[c, 2]
        rate = np.sqrt(wx * wx + wy * wy + wz * wz)
        kx, ky, kz = (wx / rate, wy / rate, wz / rate) if rate > 0.0 else (0.0, 0.0, 1.0)
        count[:] = 0.0
        sums[:] = 0.0
        squares[:] = 0.0
        for i in range(n):
            angle = -rate * dts[i]
            cos, sin = np.cos(angle), np.sin(angle)
            dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
            along = (kx * dx + ky * dy + kz * dz) * (1.0 - cos)
            ux = dx * cos + (ky * dz - kz * dy) * sin + kx * along
            uy = dy * cos + (kz * dx - kx * dz) * sin + ky * along
            uz = dz * cos + (kx * dy - ky * dx) * sin + kz * along
            cell = 0
            for v in (ux, uy, uz):
                j = int((v + 1.0) * 0.5 * patches)
                cell = cell * patches + min(max(j, 0), patches - 1)
            count[cell] += 1.0
            for j in range(3):
                sums[cell, j] += chroma[i, j]
                squares[cell] += chroma[i, j] * chroma[i, j]
        spread = 0.0
        for cell in range(cells):
            if count[cell] > 0.0:
                spread += squares[cell] - (sums[cell, 0] ** 2 + sums[cell, 1] ** 2
                                           + sums[cell, 2] ** 2) / count[cell]
        out[c] = spread / n
    return out


def _search(samples: SurfaceSamples, centre_time: float, max_rate: float, window: float,
            keep: int = 4) -> list[np.ndarray]:
    """The `keep` best distinct candidates of a grid of 300 directions (12 degrees apart) x
    rates (steps that turn the body 0.12 rad more across the window) on the coarse patches."""
    rates = np.arange(0.12 / window, max_rate, 0.12 / window)
    cands = (sphere_directions(300)[:, None] * rates[None, :, None]).reshape(-1, 3)
    errs = texture_misfit(cands, samples, centre_time, SEARCH_PATCHES)
    picks: list[int] = []
    for i in np.argsort(errs):
        if all(np.linalg.norm(cands[i] - cands[j]) > 0.24 / window for j in picks):
            picks.append(int(i))
        if len(picks) == keep:
            break
    return [cands[i] for i in picks]


def _refine(omegas, samples: SurfaceSamples, centre_time: float, step: float,
            rounds: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A pattern search about each of `omegas` (k, 3): steps of `step` along each axis and
    its opposite, halved each round; (k, 3) and their misfits."""
    omegas = np.array(omegas, np.float64).reshape(-1, 3)
    err = texture_misfit(omegas, samples, centre_time)
    moves = np.concatenate([np.eye(3), -np.eye(3)])
    for _ in range(rounds):
        for _ in range(3):
            probes = (omegas[:, None] + step * moves[None]).reshape(-1, 3)
            e = texture_misfit(probes, samples, centre_time).reshape(len(omegas), 6)
            best = e.argmin(1)
            better = e[np.arange(len(omegas)), best] < err
            omegas = np.where(better[:, None], probes.reshape(len(omegas), 6, 3)[
                np.arange(len(omegas)), best], omegas)
            err = np.where(better, e[np.arange(len(omegas)), best], err)
        step *= 0.5
    return omegas, err


def estimate_texture_spin(samples: SurfaceSamples, spacing: float, radius: float) -> Spin:
    """The Spin of a ball of `radius` seen as `samples` (`surface_samples`): searched on the
    window of WINDOWS[0] about the samples' middle time, refined on each wider one; `spacing`
    the frame spacing (rates up to MAX_TURN_PER_FRAME a spacing). Its spread is what a
    ball's blobs show (radius^2 / 4 each way, `nehad.spin_tracks.ball_radius`); `fit` and
    `fit_still` the misfits of the spin and of none over every sample."""
    times = samples.times
    spread = np.eye(3) * radius * radius / 4.0
    if not len(times):
        return Spin(np.zeros(3), 0.0, spread, 0.0, 0.0, round=True)
    centre = 0.5 * (float(times.min()) + float(times.max()))
    best = None
    for window in WINDOWS:
        inside = np.abs(times - centre) <= window
        if inside.sum() < MIN_SAMPLES:  # a track with a gap about its middle
            continue
        part = SurfaceSamples(times[inside], samples.directions[inside], samples.chroma[inside])
        if best is None:
            best = _search(part, centre, MAX_TURN_PER_FRAME / spacing, min(window, 1.0))
        span = max(float(np.abs(part.times - centre).max()), spacing)
        refined, errs = _refine(np.stack(best), part, centre, 0.06 / span)
        best = list(refined[np.argsort(errs, kind="stable")])
    if best is None:
        return Spin(np.zeros(3), centre, spread, 0.0, 0.0, round=True)
    fit, still = texture_misfit(np.stack([best[0], np.zeros(3)]), samples, centre)
    return Spin(best[0], centre, spread, float(fit), float(still), round=True)


__all__ = ["SurfaceSamples", "estimate_texture_spin", "surface_samples", "texture_misfit"]
