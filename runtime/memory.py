"""A memory bound for rendering (issue 15): estimate what a frame needs before drawing it, and
refuse with one message what would not fit, instead of paging the machine to a halt.

What a frame of W x H pixels and N Gaussians takes (the buffers of :mod:`nehad.runtime.raster`
and of the writers, measured from the code, rounded up):

* images: :data:`BYTES_PER_PIXEL` per pixel: the rasterizer's rgb, final transmittance, depth,
  stopping index and alpha (28 bytes), plus the float copy and 8-bit quantisation the image
  writers and the video encoder make (52 bytes);
* Gaussians: :data:`BYTES_PER_GAUSSIAN` each: float32 inputs, the projection (means2d, conic,
  colour, depth, radius) and the binning records (tile rectangle, 64-byte packed record, depth
  order);
* tile lists: the per-tile counters of every binning thread (16 bytes a tile and thread), and 4
  bytes per (Gaussian, tile) pair: at least one tile per Gaussian before binning; the exact count
  is checked again by :func:`check_tile_lists` once the Gaussians are binned, before the lists
  are allocated.

The limit is the memory available to this process: Linux's ``MemAvailable`` (free memory plus
what the kernel can reclaim), lowered by a cgroup (container) limit when there is one. Setting
``$NEHAD_MAX_FRAME_MEMORY`` (bytes, or with a unit: ``512M``, ``8G``) replaces it with a cap of
your choice. Where neither can be known (no /proc), nothing is refused.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from .errors import InputProblem

__all__ = ["BYTES_PER_GAUSSIAN", "BYTES_PER_PIXEL", "BYTES_PER_WORKER", "CAP_ENV", "FrameMemoryError", "FrameMemory",
           "available_memory", "check_cloud_memory", "check_frame_memory", "check_plan_memory",
           "check_tile_lists", "estimate_frame", "format_bytes", "memory_limit"]

BYTES_PER_PIXEL = 80
BYTES_PER_GAUSSIAN = 400
TILE = 16
CAP_ENV = "NEHAD_MAX_FRAME_MEMORY"
# needs below this size are not checked unless a cap is set (no /proc reads for small frames)
_SMALL = 64 << 20


class FrameMemoryError(InputProblem):
    """A frame (or cloud) would need more memory than is available; the message names the input
    and both figures."""


def format_bytes(n: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _parse_bytes(text: str) -> int:
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kKmMgGtT]?)[iI]?[bB]?\s*", text)
    if not m:
        raise FrameMemoryError(f"{CAP_ENV}={text!r}: expected a number of bytes, e.g. 8G or "
                               f"512M")
    scale = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}[m.group(2).lower()]
    value = int(float(m.group(1)) * scale)
    if value <= 0:
        raise FrameMemoryError(f"{CAP_ENV}={text!r}: must be more than 0")
    return value


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_room() -> int | None:
    """Bytes left under this process's cgroup memory limit (v2, else v1), or None."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) == 3 and parts[0] == "0" and parts[1] == "":  # cgroup v2
            base = Path("/sys/fs/cgroup") / parts[2].lstrip("/")
            limit, used = _read_int(base / "memory.max"), _read_int(base / "memory.current")
            if limit is not None and used is not None:
                return max(0, limit - used)
    base = Path("/sys/fs/cgroup/memory")
    limit = _read_int(base / "memory.limit_in_bytes")
    used = _read_int(base / "memory.usage_in_bytes")
    if limit is not None and used is not None and limit < (1 << 60):
        return max(0, limit - used)
    return None


def available_memory() -> int | None:
    """Bytes this process can still take (module doc), or None when unknown."""
    avail = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        avail = None
    room = _cgroup_room()
    if room is not None:
        avail = room if avail is None else min(avail, room)
    return avail


def memory_limit() -> tuple[int | None, str]:
    """(bytes a render may take, where that figure comes from)."""
    cap = os.environ.get(CAP_ENV)
    if cap:
        return _parse_bytes(cap), f"the cap {CAP_ENV}={cap}"
    return available_memory(), "the memory available"


@dataclass
class FrameMemory:
    width: int
    height: int
    gaussians: int
    images: int
    gaussian_buffers: int
    tile_lists: int

    @property
    def total(self) -> int:
        return self.images + self.gaussian_buffers + self.tile_lists

    def describe(self) -> str:
        return (f"images {format_bytes(self.images)}, Gaussians "
                f"{format_bytes(self.gaussian_buffers)}, tile lists at least "
                f"{format_bytes(self.tile_lists)}")


def estimate_frame(width: int, height: int, gaussians: int, out_width: int | None = None,
                   threads: int | None = None) -> FrameMemory:
    """The memory of one frame (module doc); `out_width`: the written image's width when it
    differs (side by side with the ground truth)."""
    w, h, n = int(width), int(height), max(0, int(gaussians))
    out_w = int(out_width) if out_width is not None else w
    if threads is None:
        threads = _threads()
    tiles = -(-w // TILE) * -(-h // TILE)
    images = 28 * w * h + (BYTES_PER_PIXEL - 28) * out_w * h
    return FrameMemory(w, h, n, images, BYTES_PER_GAUSSIAN * n,
                       16 * tiles * max(1, threads) + 8 * tiles + 4 * n)


def _threads() -> int:
    try:
        import numba

        return int(numba.get_num_threads())
    except Exception:  # numba missing or not initialised: assume every core
        return os.cpu_count() or 1


def _refuse(what: str, need: int, detail: str, advice: str, verb: str = "needs") -> None:
    if need < _SMALL and not os.environ.get(CAP_ENV):
        return
    limit, where = memory_limit()
    if limit is None or need <= limit:
        return
    raise FrameMemoryError(f"{what} {verb} about {format_bytes(need)} of memory ({detail}), more "
                           f"than {where} ({format_bytes(limit)}); {advice}")


#: What a pool worker process takes before its first frame (Python, numpy, numba, onnxruntime
#: and the model; measured about 200 MB): `--workers 1000` must not start 1000 of them
BYTES_PER_WORKER = 200 << 20


def check_frame_memory(width: int, height: int, gaussians: int, what: str,
                       parallel: int = 1, out_width: int | None = None,
                       advice: str | None = None) -> FrameMemory:
    """Refuse (FrameMemoryError) a frame, or `parallel` frames drawn at once by as many worker
    processes, that would not fit (module doc). `what` names the input in the message (e.g.
    ``--size 32768x32768``)."""
    est = estimate_frame(width, height, gaussians, out_width)
    parallel = max(1, int(parallel))
    detail = est.describe() + (f"; {parallel} frames drawn at once by as many processes of about "
                               f"{format_bytes(BYTES_PER_WORKER)} each" if parallel > 1 else "")
    if advice is None:
        advice = "render a smaller size" + (" or use fewer workers" if parallel > 1 else "") + \
                 f" (or set {CAP_ENV})"
    frames = f"{parallel} {est.width}x{est.height} frames" if parallel > 1 else \
        f"a {est.width}x{est.height} frame"
    workers = BYTES_PER_WORKER * parallel if parallel > 1 else 0
    _refuse(f"{what}: {frames} of {est.gaussians} Gaussians", est.total * parallel + workers,
            detail, advice, "need" if parallel > 1 else "needs")
    return est


def check_tile_lists(pairs: int, width: int, height: int, n_chunks: int) -> None:
    """Refuse binning whose tile lists (`pairs` Gaussian-tile entries) would not fit; called by
    the rasterizer between counting and allocating them."""
    tiles = -(-int(width) // TILE) * -(-int(height) // TILE)
    need = 4 * int(pairs) + 16 * tiles * max(1, int(n_chunks)) + 8 * tiles
    _refuse(f"a {width}x{height} frame: its tile lists", need, f"{pairs} Gaussian-tile entries",
            f"render a smaller size (or set {CAP_ENV})", verb="need")


#: What one planned frame of a video takes before anything is drawn: its camera, time, task and
#: result records (measured: 100 MB for 100000 frames; doubled)
BYTES_PER_PLANNED_FRAME = 2048


def check_plan_memory(frames: int, what: str, plan: str | None = None) -> None:
    """Refuse a frame count whose plan alone would not fit (issue 26: ``--frames 30000000``
    planned silently for hours before it would have run out of memory). `plan` says what is
    planned (default: ``the plan of N frames``)."""
    _refuse(f"{what}: {plan or f'the plan of {frames} frames'}",
            BYTES_PER_PLANNED_FRAME * max(0, int(frames)), "cameras, times and tasks",
            f"ask for fewer (or set {CAP_ENV})", verb="needs")


def check_cloud_memory(gaussians: int, sh_degree: int, what: str) -> None:
    """Refuse a Gaussian cloud whose arrays and writers' copies (3 copies of the float32
    attributes) would not fit; `nehad ply` writes one cloud per frame."""
    k = (int(sh_degree) + 1) ** 2
    need = 3 * 4 * (14 + 3 * k) * max(0, int(gaussians))
    _refuse(f"{what}: {gaussians} Gaussians", need, "attributes and the writer's copies",
            f"the model is too large for this machine (or set {CAP_ENV})", verb="need")
