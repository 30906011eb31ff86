"""Line plots and colour maps drawn with numpy and OpenCV (matplotlib is not a dependency).

    img = line_plot([{"x": steps, "y": loss, "label": "loss"}], title="Training loss",
                    xlabel="step", ylabel="loss", logy=True, vlines=[(3000, "fine")])
    write_image("loss.png", img / 255.0)          # or encode_png(img) for a report

Images are RGB uint8 arrays (H, W, 3). Lines are anti-aliased and drawn with sub-pixel precision
(OpenCV's fixed-point `shift`); gaps (NaN) break a line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# A qualitative palette (RGB 0-255) for plot series; colour-blind friendly (Okabe-Ito).
PALETTE = ((0, 114, 178), (213, 94, 0), (0, 158, 115), (204, 121, 167), (230, 159, 0),
           (86, 180, 233), (120, 120, 120), (240, 228, 66))

_FONT = None  # cv2.FONT_HERSHEY_SIMPLEX, set on first use (cv2 is imported lazily)
_SHIFT = 4  # sub-pixel bits for cv2 drawing
_S = 1 << _SHIFT


def _cv2():
    import cv2

    global _FONT
    _FONT = cv2.FONT_HERSHEY_SIMPLEX
    return cv2


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """About `count` round tick values (1, 2, 5 x 10^k steps) covering [lo, hi]."""
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        return [lo]
    raw = (hi - lo) / max(count, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    ticks, v = [], first
    while v <= hi + step * 1e-9:
        ticks.append(0.0 if abs(v) < step * 1e-9 else v)
        v += step
    return ticks


def format_tick(v: float) -> str:
    """Short label for a tick value: 0.05, 1.5, 200, 2k, 1.2M, 1e-04."""
    a = abs(v)
    if a == 0:
        return "0"
    if a >= 1e6:
        return f"{v / 1e6:g}M"
    if a >= 1e4:
        return f"{v / 1e3:g}k"
    if a < 1e-3:
        return f"{v:.0e}"
    return f"{v:.4g}"


def text_size(text: str, scale: float = 0.45, thickness: int = 1) -> tuple[int, int]:
    cv2 = _cv2()
    (w, h), base = cv2.getTextSize(text, _FONT, scale, thickness)
    return w, h + base


def put_text(img: np.ndarray, text: str, org, color=(30, 30, 30), scale: float = 0.45,
             thickness: int = 1, anchor: str = "left") -> None:
    """Draw `text` with its baseline at org = (x, y); anchor left, center or right."""
    cv2 = _cv2()
    (w, _), _ = cv2.getTextSize(text, _FONT, scale, thickness)
    x, y = org
    if anchor == "center":
        x -= w // 2
    elif anchor == "right":
        x -= w
    cv2.putText(img, text, (int(x), int(y)), _FONT, scale, tuple(int(c) for c in color),
                thickness, cv2.LINE_AA)


def _segments(px: np.ndarray, py: np.ndarray) -> list[np.ndarray]:
    """Runs of finite points as int32 (K, 1, 2) arrays in fixed point."""
    ok = np.isfinite(px) & np.isfinite(py)
    out, start = [], None
    for i, good in enumerate(list(ok) + [False]):
        if good and start is None:
            start = i
        elif not good and start is not None:
            pts = np.stack([px[start:i], py[start:i]], 1)
            out.append(np.round(pts * _S).astype(np.int32).reshape(-1, 1, 2))
            start = None
    return out


def _dashed_vline(img, x: int, y0: int, y1: int, color, dash: int = 5) -> None:
    cv2 = _cv2()
    for y in range(y0, y1, 2 * dash):
        cv2.line(img, (x, y), (x, min(y + dash, y1)), color, 1, cv2.LINE_AA)


_GRID, _AXIS, _INK = (232, 232, 232), (90, 90, 90), (40, 40, 40)
_LEFT, _RIGHT = 64, 16  # margins of the plot area (pixels)


@dataclass(frozen=True)
class _Axes:
    """The plot area (`left`, `top`, `pw` x `ph` pixels) and the data range it shows."""

    left: int
    top: int
    pw: int
    ph: int
    x0: float
    x1: float
    y0: float
    y1: float

    def X(self, v):
        return self.left + (np.asarray(v, np.float64) - self.x0) / (self.x1 - self.x0) * self.pw

    def Y(self, v):
        return (self.top + self.ph
                - (np.asarray(v, np.float64) - self.y0) / (self.y1 - self.y0) * self.ph)


def _series_color(s: dict, k: int) -> tuple:
    """The RGB colour of series `k`: its "color", or the palette's."""
    return tuple(int(c) for c in s.get("color", PALETTE[k % len(PALETTE)]))


def _plot_box(width: int, height: int, title: str, xlabel: str) -> tuple[int, int, int]:
    """Top margin, width and height of the plot area; ValueError when it is too small."""
    top = 34 if title else 14
    bottom = 44 if xlabel else 30
    pw, ph = width - _LEFT - _RIGHT, height - top - bottom
    if pw < 20 or ph < 20:
        raise ValueError(f"line_plot: size {width}x{height} is too small")
    return top, pw, ph


def _series_data(series, logy: bool) -> list[tuple[np.ndarray, np.ndarray, dict]]:
    """(x, y, series) per series as float64 arrays; with `logy`, y as log10 (NaN where <= 0)."""
    data = []
    for k, s in enumerate(series):
        x = np.asarray(s["x"], np.float64).reshape(-1)
        y = np.asarray(s["y"], np.float64).reshape(-1)
        if x.shape != y.shape:
            raise ValueError(f"line_plot: series {k}: x has {x.size} values, y {y.size}")
        if logy:
            y = np.where(y > 0, y, np.nan)
            y = np.log10(y)
        data.append((x, y, s))
    return data


def _x_range(data) -> tuple[float, float]:
    """The x range of the points with a finite y (widened when empty or a single value)."""
    xs = np.concatenate([d[0][np.isfinite(d[1])] for d in data]) if data else np.zeros(0)
    xs = xs[np.isfinite(xs)]
    if xs.size == 0:
        x0, x1 = 0.0, 1.0
    else:
        x0, x1 = float(xs.min()), float(xs.max())
    if x1 <= x0:
        x0, x1 = x0 - 0.5, x1 + 0.5
    return x0, x1


def _y_range(data, logy: bool, ylim) -> tuple[float, float]:
    """`ylim` (log10 with `logy`), else the finite y values' range with a 5 % margin."""
    ys = np.concatenate([d[1][np.isfinite(d[1])] for d in data]) if data else np.zeros(0)
    if ylim is not None:
        y0, y1 = (math.log10(v) if logy else float(v) for v in ylim)
    elif ys.size == 0:
        y0, y1 = 0.0, 1.0
    else:
        y0, y1 = float(ys.min()), float(ys.max())
        pad = 0.05 * (y1 - y0) if y1 > y0 else (0.5 if not logy else 0.25)
        y0, y1 = y0 - pad, y1 + pad
    return y0, y1


def _y_ticks(y0: float, y1: float, logy: bool) -> tuple[list[float], list[str]]:
    """Tick values on the y axis and their labels (powers of ten on a log axis)."""
    if logy:
        lo_e, hi_e = math.floor(y0), math.ceil(y1)
        yt = [float(e) for e in range(lo_e, hi_e + 1) if y0 <= e <= y1]
        if len(yt) < 2:  # narrow range: 1-2-5 ticks in linear values
            yt = [math.log10(v) for v in nice_ticks(10 ** y0, 10 ** y1) if v > 0]
        return yt, [format_tick(10 ** v) for v in yt]
    yt = nice_ticks(y0, y1)
    return yt, [format_tick(v) for v in yt]


def _draw_grid(img: np.ndarray, ax: _Axes, logy: bool) -> None:
    """Grid lines, ticks with their labels and the frame of the plot area."""
    cv2 = _cv2()
    left, top, pw, ph = ax.left, ax.top, ax.pw, ax.ph
    for v, lab in zip(*_y_ticks(ax.y0, ax.y1, logy)):
        py = int(round(float(ax.Y(v))))
        if top <= py <= top + ph:
            cv2.line(img, (left, py), (left + pw, py), _GRID, 1)
            cv2.line(img, (left - 4, py), (left, py), _AXIS, 1)
            put_text(img, lab, (left - 7, py + 4), _INK, 0.38, anchor="right")
    for v in nice_ticks(ax.x0, ax.x1, 6):
        px = int(round(float(ax.X(v))))
        if left <= px <= left + pw:
            cv2.line(img, (px, top), (px, top + ph), _GRID, 1)
            cv2.line(img, (px, top + ph), (px, top + ph + 4), _AXIS, 1)
            put_text(img, format_tick(v), (px, top + ph + 17), _INK, 0.38, anchor="center")
    cv2.rectangle(img, (left, top), (left + pw, top + ph), _AXIS, 1)


def _draw_vlines(img: np.ndarray, ax: _Axes, vlines) -> None:
    """The dashed vertical markers (x, label) inside the plot area."""
    for xv, lab in vlines:
        px = int(round(float(ax.X(xv))))
        if ax.left <= px <= ax.left + ax.pw:
            _dashed_vline(img, px, ax.top + 1, ax.top + ax.ph, (150, 150, 150))
            if lab:
                put_text(img, str(lab), (px + 4, ax.top + 13), (110, 110, 110), 0.38)


def _draw_series(img: np.ndarray, ax: _Axes, data) -> None:
    """The lines (and markers), clipped to the plot area."""
    cv2 = _cv2()
    area = img[ax.top:ax.top + ax.ph + 1, ax.left:ax.left + ax.pw + 1]
    for k, (x, y, s) in enumerate(data):
        color = _series_color(s, k)
        thick = int(s.get("width", 2))
        px, py = ax.X(x) - ax.left, ax.Y(y) - ax.top
        segs = _segments(px, py)
        if segs:
            cv2.polylines(area, segs, False, color, thick, cv2.LINE_AA, _SHIFT)
        if s.get("markers") or (segs and all(len(g) == 1 for g in segs)):
            for g in segs:
                for p in g.reshape(-1, 2):
                    cv2.circle(area, (int(p[0]), int(p[1])), 3 * _S, color, -1, cv2.LINE_AA,
                               _SHIFT)


def _draw_ylabel(img: np.ndarray, ax: _Axes, ylabel: str) -> None:
    """The y axis label, rotated: drawn on a strip that is turned a quarter and pasted."""
    height = img.shape[0]
    w_t, h_t = text_size(ylabel, 0.42)
    strip = np.full((h_t + 6, w_t + 6, 3), 255, np.uint8)
    put_text(strip, ylabel, (3, h_t), _INK, 0.42)
    rot = np.ascontiguousarray(np.rot90(strip))
    y_start = max(ax.top, ax.top + ax.ph // 2 - rot.shape[0] // 2)
    y_end = min(height, y_start + rot.shape[0])
    img[y_start:y_end, 2:2 + rot.shape[1]] = rot[:y_end - y_start]


def _draw_labels(img: np.ndarray, ax: _Axes, title: str, xlabel: str, ylabel: str) -> None:
    """Title, x label and y label, each when given."""
    if title:
        put_text(img, title, (ax.left, 22), _INK, 0.55, 1)
    if xlabel:
        put_text(img, xlabel, (ax.left + ax.pw // 2, img.shape[0] - 8), _INK, 0.42,
                 anchor="center")
    if ylabel:
        _draw_ylabel(img, ax, ylabel)


def _legend_row(img: np.ndarray, items, widths, title: str) -> None:
    """The legend in one row at the top right, outside the axes."""
    cv2 = _cv2()
    x = img.shape[1] - _RIGHT - sum(widths)
    yy = 22 if title else 11
    for (lab, color), wd in zip(items, widths):
        cv2.line(img, (x + 4, yy - 4), (x + 22, yy - 4), color, 2, cv2.LINE_AA)
        put_text(img, lab, (x + 27, yy), _INK, 0.4)
        x += wd


def _plotted_points(ax: _Axes, data) -> np.ndarray:
    """(N, 2) finite pixel positions of the series: vertices and points along the segments."""
    pts = []
    for x, y, _ in data:
        p = np.stack([ax.X(x), ax.Y(y)], 1)
        f = np.linspace(0.0, 1.0, 9)[:, None, None]
        pts.append(p.reshape(-1, 2) if len(p) < 2 else
                   (p[:-1][None] * (1 - f) + p[1:][None] * f).reshape(-1, 2))
    pts = np.concatenate(pts) if pts else np.zeros((0, 2))
    return pts[np.isfinite(pts).all(1)]


def _legend_corner(ax: _Axes, data, bw: int, bh: int) -> tuple[int, int]:
    """The corner of the plot area whose `bw` x `bh` box covers the fewest data points."""
    pts = _plotted_points(ax, data)
    left, top, pw, ph = ax.left, ax.top, ax.pw, ax.ph
    corners = [(left + pw - bw - 6, top + 6), (left + 6, top + 6),
               (left + pw - bw - 6, top + ph - bh - 6), (left + 6, top + ph - bh - 6)]

    def covered(c):
        return int(((pts[:, 0] >= c[0] - 4) & (pts[:, 0] <= c[0] + bw + 4)
                    & (pts[:, 1] >= c[1] - 4) & (pts[:, 1] <= c[1] + bh + 4)).sum())

    return min(corners, key=covered)


def _legend_box(img: np.ndarray, ax: _Axes, data, items) -> None:
    """The legend in a framed box in the emptiest corner of the plot area."""
    cv2 = _cv2()
    wmax = max(text_size(lab, 0.4)[0] for lab, _ in items)
    bw, bh = wmax + 38, 18 * len(items) + 8
    bx, by = _legend_corner(ax, data, bw, bh)
    cv2.rectangle(img, (bx, by), (bx + bw, by + bh), (255, 255, 255), -1)
    cv2.rectangle(img, (bx, by), (bx + bw, by + bh), (200, 200, 200), 1)
    for i, (lab, color) in enumerate(items):
        yy = by + 14 + 18 * i
        cv2.line(img, (bx + 6, yy - 4), (bx + 26, yy - 4), color, 2, cv2.LINE_AA)
        put_text(img, lab, (bx + 32, yy), _INK, 0.4)


def _draw_legend(img: np.ndarray, ax: _Axes, data, title: str) -> None:
    """The labelled series' legend: preferably in one row right of the title, outside the
    axes; else in a box inside them."""
    items = [(s.get("label"), _series_color(s, k))
             for k, (_, _, s) in enumerate(data) if s.get("label")]
    widths = [text_size(lab, 0.4)[0] + 34 for lab, _ in items]
    title_w = text_size(title, 0.55)[0] if title else 0
    if items and ax.left + title_w + 16 + sum(widths) <= img.shape[1] - _RIGHT:
        _legend_row(img, items, widths, title)
    elif items:
        _legend_box(img, ax, data, items)


def line_plot(series, *, title: str = "", xlabel: str = "", ylabel: str = "",
              size: tuple[int, int] = (640, 360), logy: bool = False, vlines=(),
              ylim: tuple[float, float] | None = None, legend: bool = True) -> np.ndarray:
    """A line plot as an RGB uint8 image of `size` = (width, height).

    series: dicts with "x", "y" (sequences of equal length), optional "label", "color" (RGB
    0-255; default the palette), "width" (line thickness, default 2) and "markers" (bool: a dot
    at each point). logy: logarithmic y axis (values <= 0 are left out). vlines: (x, label) pairs
    drawn as dashed vertical markers (e.g. where the fine stage starts). ylim: fixed y range.
    """
    _cv2()
    width, height = int(size[0]), int(size[1])
    img = np.full((height, width, 3), 255, np.uint8)
    top, pw, ph = _plot_box(width, height, title, xlabel)
    data = _series_data(series, logy)
    ax = _Axes(_LEFT, top, pw, ph, *_x_range(data), *_y_range(data, logy, ylim))
    _draw_grid(img, ax, logy)
    _draw_vlines(img, ax, vlines)
    _draw_series(img, ax, data)
    _draw_labels(img, ax, title, xlabel, ylabel)
    if legend:
        _draw_legend(img, ax, data, title)
    return img


def ema(values, alpha: float = 0.1) -> np.ndarray:
    """Exponential moving average (NaN-aware) for noisy training curves."""
    v = np.asarray(values, np.float64)
    out = np.empty_like(v)
    acc = np.nan
    for i, x in enumerate(v):
        if np.isfinite(x):
            acc = x if not np.isfinite(acc) else (1 - alpha) * acc + alpha * x
        out[i] = acc
    return out


def colormap(values, name: str = "turbo") -> np.ndarray:
    """(N,) values in [0, 1] -> (N, 3) float32 RGB in [0, 1] through an OpenCV colour map
    ("turbo", "viridis", "inferno", "plasma", ...). NaN maps to 0."""
    cv2 = _cv2()
    v = np.clip(np.nan_to_num(np.asarray(values, np.float64).reshape(-1), nan=0.0), 0.0, 1.0)
    code = getattr(cv2, f"COLORMAP_{name.upper()}", None)
    if code is None:
        raise ValueError(f"colormap: unknown colour map {name!r}")
    idx = np.round(v * 255).astype(np.uint8).reshape(-1, 1)
    bgr = cv2.applyColorMap(idx, code).reshape(-1, 3)
    return (bgr[:, ::-1].astype(np.float32) / 255.0)


# Static -> dynamic colours of BED weight maps: blue (0), light grey (0.5), red (1).
_WEIGHT_STOPS = np.array([[0.19, 0.33, 0.80], [0.86, 0.86, 0.86], [0.84, 0.12, 0.10]], np.float32)


def weight_colors(values) -> np.ndarray:
    """(...) weights in [0, 1] -> (..., 3) RGB in [0, 1]: static blue, mid grey, dynamic red."""
    v = np.clip(np.nan_to_num(np.asarray(values, np.float32), nan=0.0), 0.0, 1.0)
    lo = np.clip(v * 2.0, 0.0, 1.0)[..., None]
    hi = np.clip(v * 2.0 - 1.0, 0.0, 1.0)[..., None]
    a, b, c = _WEIGHT_STOPS
    return np.where(v[..., None] <= 0.5, a + (b - a) * lo, b + (c - b) * hi).astype(np.float32)


def colorbar(width: int, height: int, colors_fn, left_label: str, right_label: str,
             ticks=(0.0, 0.5, 1.0)) -> np.ndarray:
    """A horizontal colour bar with labels as an RGB float image (height >= 30) in [0, 1]."""
    width, height = int(width), max(int(height), 30)
    img = np.full((height, width, 3), 255, np.uint8)
    bar_h = max(8, height - 22)
    x0, x1 = 8, max(width - 8, 9)
    ramp = colors_fn(np.linspace(0.0, 1.0, x1 - x0))
    img[2:2 + bar_h, x0:x1] = np.round(ramp * 255).astype(np.uint8)[None, :, :]
    y = 2 + bar_h + 14
    scale = 0.4 if width >= 200 else 0.33
    put_text(img, left_label, (x0, y), (40, 40, 40), scale)
    put_text(img, right_label, (x1, y), (40, 40, 40), scale, anchor="right")
    room = x1 - x0 - text_size(left_label, scale)[0] - text_size(right_label, scale)[0]
    if room > 40 * len(ticks[1:-1]):  # middle ticks only where they do not run into the labels
        for t in ticks[1:-1]:
            put_text(img, f"{t:g}", (int(x0 + t * (x1 - x0)), y), (40, 40, 40), scale,
                     anchor="center")
    return img.astype(np.float32) / 255.0


def encode_png(image) -> bytes:
    """PNG bytes of an RGB(A) image: uint8 as is, float in [0, 1] scaled to 8 bits."""
    cv2 = _cv2()
    a = np.asarray(image)
    if a.dtype != np.uint8:
        a = np.round(np.clip(np.nan_to_num(a.astype(np.float32)), 0.0, 1.0) * 255).astype(np.uint8)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[2] == 3:
        a = a[:, :, ::-1]
    elif a.shape[2] == 4:
        a = a[:, :, [2, 1, 0, 3]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a))
    if not ok:
        raise ValueError("encode_png: OpenCV could not encode the image")
    return buf.tobytes()


def to_uint8(image) -> np.ndarray:
    """Float [0, 1] (or uint8) RGB image -> uint8."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    return np.round(np.clip(np.nan_to_num(a.astype(np.float32)), 0.0, 1.0) * 255).astype(np.uint8)


__all__ = ["PALETTE", "colorbar", "colormap", "ema", "encode_png", "format_tick", "line_plot",
           "nice_ticks", "put_text", "text_size", "to_uint8", "weight_colors"]
