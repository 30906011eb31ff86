"""What each training step may look at: the time curriculum and the resolution warm-up
(docs/training.md, "The recipe").

Time curriculum. The MuJoCo objects move by many times their own size, and a Gaussian that is
more than its own width away from the object it should follow gets no gradient from it. So the
coarse stage fits static Gaussians only to the frames near `train.canonical_time` (a window
short enough that the objects barely move in it, long enough to hold every camera of a
monocular rig), and the fine stage starts from that window and widens it step by step to the
whole time range: every newly admitted time is close to one the field already places correctly,
so the objects are followed instead of lost.

While the window is narrower than the time range, the space-time hex-plane rows outside it are
held at the values of the window's edge rows (`hold_time_planes`); a time entering the window
then starts from the deformation of the nearest trained time.

A monocular capture has one camera per time, so the window is widened until it holds at least
`min_window_frames` frames (`widen_to_frames`): a short window must still show the static
stage enough viewpoints.

Resolution warm-up. `data.resolution_schedule` lists (fraction of all steps, extra downscale
factor) pairs; early steps render 1/4 or 1/16 of the pixels, but never fewer than
`data.warmup_min_size` pixels along the shorter side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from nehad.config import HOLD_MODES


@dataclass(frozen=True)
class TimeWindow:
    """The closed interval of times [lo, hi] a step may draw frames from."""

    lo: float
    hi: float

    def contains(self, t: float) -> bool:
        return self.lo - 1e-9 <= t <= self.hi + 1e-9


def window_at(stage, it: int, length: int, centre: float, time_range) -> TimeWindow:
    """The time window of iteration `it` (0-based) of a stage of `length` iterations
    (StageConfig fields `time_window`, `window_growth`; nehad.config), centred on `centre`.

    The half-width starts at `time_window` and grows linearly to the half-width that covers
    `time_range` when `window_growth` of the stage is done; a window of 1 covers every time."""
    t0, t1 = float(time_range[0]), float(time_range[1])
    full = max(centre - t0, t1 - centre, 0.0)
    half = min(float(stage.time_window), full) if stage.time_window < 1.0 else full
    if stage.window_growth > 0 and half < full:
        grow_steps = stage.window_growth * max(length, 1)
        half += (full - half) * min(it / grow_steps, 1.0)
    elif stage.window_growth > 0:
        half = full
    if half >= full:
        return TimeWindow(t0, t1)
    return TimeWindow(max(centre - half, t0), min(centre + half, t1))


def eligible_frames(times, window: TimeWindow, minimum: int = 1) -> np.ndarray:
    """Indices of the frames whose time lies in `window`; if fewer than `minimum` do, the
    `minimum` frames nearest to the window's centre."""
    times = np.asarray(times, np.float64)
    inside = np.flatnonzero((times >= window.lo - 1e-9) & (times <= window.hi + 1e-9))
    if len(inside) >= minimum or len(times) == 0:
        return inside
    centre = 0.5 * (window.lo + window.hi)
    return np.sort(np.argsort(np.abs(times - centre), kind="stable")[:min(minimum, len(times))])


def widen_to_frames(window: TimeWindow, times, minimum: int) -> TimeWindow:
    """`window`, widened if needed so that it holds at least `minimum` frames (the ones nearest
    to its centre). A monocular capture has one camera per time, so a window that is short in
    time can hold too few viewpoints to fit a static scene: the MuJoCo captures hold 12-15
    frames within 0.06 of t = 0.5, the D-NeRF lego scene 6 (docs/training.md)."""
    times = np.asarray(times, np.float64)
    if minimum <= 0 or len(times) == 0:
        return window
    nearest = eligible_frames(times, window, minimum=min(minimum, len(times)))
    lo, hi = float(times[nearest].min()), float(times[nearest].max())
    return TimeWindow(min(window.lo, lo), max(window.hi, hi))


def time_plane_rows(window: TimeWindow, rows: int) -> tuple[int, int]:
    """(first, last) rows of a space-time plane with `rows` time nodes (node k at time
    k / (rows - 1), align_corners) that a time in `window` interpolates from."""
    scale = rows - 1
    first = int(math.floor(window.lo * scale + 1e-6))
    last = int(math.ceil(window.hi * scale - 1e-6))
    return max(first, 0), min(max(last, first), rows - 1)


@torch.no_grad()
def hold_time_planes(hexplane, window: TimeWindow, mode: str = "value") -> None:
    """Set the rows of every space-time plane outside `window` from its edge rows (see the
    module doc). Planes are (1, C, T, S): the height axis is time. `mode` "value": each outside
    row equals the nearest edge row; "slope": it continues the edge's last step, row e + d (e -
    e_in) at d rows past the edge e (e_in: the row inside it), so a time entering the window
    starts from the motion of its nearest trained times carried on, not stopped."""
    from nehad.field.hexplane import TIME_PLANES

    if mode not in HOLD_MODES:
        raise ValueError(f"hold mode: expected one of {HOLD_MODES}, got {mode!r}")
    for scale in hexplane.planes:
        for k in TIME_PLANES:
            plane = scale[k]
            rows = plane.shape[2]
            first, last = time_plane_rows(window, rows)
            slope = mode == "slope" and last > first  # a step needs two rows inside
            if first > 0:
                _continue_rows(plane, first, -1, first + 1 if slope else None)
            if last < rows - 1:
                _continue_rows(plane, last, +1, last - 1 if slope else None)


def _continue_rows(plane, edge: int, away: int, inner: int | None) -> None:
    """The rows of `plane` past row `edge` in direction `away` (-1: down to row 0, +1: up to the
    last row) set to the edge row, plus d times its step from row `inner` at d rows from the
    edge (`inner` None: the edge row's value alone)."""
    edge_row = plane[:, :, edge:edge + 1, :]
    lo, hi = (0, edge) if away < 0 else (edge + 1, plane.shape[2])
    if inner is None:
        plane[:, :, lo:hi, :] = edge_row
        return
    d = torch.arange(lo, hi, dtype=plane.dtype).sub_(edge).abs_().reshape(1, 1, -1, 1)
    plane[:, :, lo:hi, :] = edge_row + d * (edge_row - plane[:, :, inner:inner + 1, :])


def resolution_factor(schedule, step: int, total: int, short_side: int | None = None,
                      min_size: int = 0) -> int:
    """Extra downscale factor of (0-based) `step` of `total` (data.resolution_schedule), reduced
    if needed so that an image whose shorter side is `short_side` pixels keeps at least
    `min_size` of them (data.warmup_min_size): a 100-pixel capture is not trained at 25."""
    factor = 1
    frac = step / max(total, 1)
    for start, f in schedule:
        if frac >= start:
            factor = int(f)
    if short_side is not None and min_size > 0:
        factor = max(1, min(factor, short_side // min_size))
    return factor


__all__ = ["TimeWindow", "window_at", "eligible_frames", "widen_to_frames", "time_plane_rows",
           "hold_time_planes", "resolution_factor"]
