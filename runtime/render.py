"""Render one view of a scene and write what it produced, all or nothing (docs/design.md,
"Scenes" and "Bad inputs and atomic writes").

    scene = open_scene("model.onnx")
    camera = choose_camera(scene, "cam.json")
    view = render_view(scene, camera, scene_time(scene, camera, 0.5))
    write_all([("out.png", view.image)])

`nehad render`, `nehad ply`, the stills of `nehad batch` and every video frame go through
these functions (the frame tasks of runtime/distribute.py call :func:`render_view`).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .images import ALPHA_SUFFIXES, IMAGE_SUFFIXES  # re-exported: the stills' formats
from .scene import SceneError


@dataclass
class RenderedView:
    """One drawn view: `image` (H, W, 3) RGB over the background, or (H, W, 4) colour over
    transparency with `alpha`; `depth` the expected view depth (0 where nothing is drawn);
    `covered` whether any Gaussian reached a pixel; `seconds` of rasterization."""

    image: np.ndarray
    depth: np.ndarray
    covered: bool
    seconds: float


def render_view(scene, camera, time: float | None, background=None, sh_degree: int | None = None,
                alpha: bool = False, check_memory: str | None = None,
                out_width: int | None = None, adapt_threads: bool = True,
                cloud=None) -> RenderedView:
    """Draw `scene` at `time` (checked by the caller: runtime.scene.scene_time) through
    `camera`. `background`: default the scene's; `alpha`: colour over a transparent background
    (RGBA). `check_memory`: the input to name when the frame would not fit in memory (None: not
    checked; `out_width`: the width of the frame the image goes into, when wider).
    `adapt_threads`: draw with the threads the machine's load leaves free (runtime/threads.py);
    False when the caller set the thread count. `cloud`: the scene's Gaussians at `time` when the
    caller already has them (:func:`render_frames`)."""
    from .raster import render as rasterize

    if cloud is None:
        cloud = scene.gaussians(time)
    if check_memory is not None:
        from .memory import check_frame_memory

        check_frame_memory(camera.width, camera.height, len(cloud), check_memory,
                           out_width=out_width)
    bg = (0.0, 0.0, 0.0) if alpha else tuple(background or scene.default_background)
    start = _time.perf_counter()
    out = rasterize(cloud, camera, background=bg, sh_degree=sh_degree,
                    adapt_threads=adapt_threads)
    seconds = _time.perf_counter() - start
    image = np.concatenate([out.rgb, out.alpha[:, :, None]], axis=2) if alpha else out.rgb
    drawn = out.alpha > 0
    depth = np.where(drawn, out.depth, 0.0).astype(np.float32)
    return RenderedView(image, depth, bool(drawn.any()), seconds)


def render_frames(scene, frames, background=None, sh_degree: int | None = None,
                  alpha: bool = False, pipelined: bool = True):
    """Yield a :class:`RenderedView` for each (camera, time) of `frames`, in order: what
    :func:`render_view` draws for each. `pipelined`: while a frame is rasterized, the next
    frame's deformation runs on a second thread (onnxruntime releases the GIL), and the
    rasterizer leaves it one core (its Numba threads: the cores the load leaves free, minus one,
    at least one); best with the scene opened on one onnxruntime thread. On 2 cores a
    15k-Gaussian scene8 model at 800x800 drew 67-69 frames a second so against 55-57 one after
    the other (docs/performance.md, "Frames in a sequence")."""
    frames = list(frames)
    if not pipelined or len(frames) < 2:
        for camera, time in frames:
            yield render_view(scene, camera, time, background, sh_degree, alpha)
        return
    import numba
    from concurrent.futures import ThreadPoolExecutor

    from .threads import frame_threads

    caller_threads = numba.get_num_threads()
    with ThreadPoolExecutor(1, thread_name_prefix="nehad-deform") as pool:
        pending = pool.submit(scene.gaussians, frames[0][1])
        try:
            for k, (camera, time) in enumerate(frames):
                cloud = pending.result()
                if k + 1 < len(frames):
                    pending = pool.submit(scene.gaussians, frames[k + 1][1])
                numba.set_num_threads(caller_threads)
                cores = frame_threads()  # what the load leaves free, as render_view would
                numba.set_num_threads(max(1, cores - (k + 1 < len(frames))))
                yield render_view(scene, camera, time, background, sh_degree, alpha,
                                  adapt_threads=False, cloud=cloud)
        finally:
            pending.cancel()
            numba.set_num_threads(caller_threads)


def check_output(path: Path, suffixes, what: str, input: str = "output") -> None:
    """Refuse an output path before any work: an unknown format, a missing folder, a folder."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise SceneError(f"{{{input}}} {path}: {what} must end in {', '.join(suffixes)}", input)
    if not path.parent.is_dir():
        raise SceneError(f"{{{input}}} {path}: output folder {path.parent} does not exist", input)
    if path.is_dir():
        raise SceneError(f"{{{input}}} {path}: is a folder", input)


def write_all(outputs) -> None:
    """Write each (path, array-or-writer) atomically; if one fails, remove those this call
    already wrote, so a failed command leaves no partial set. An array is written as an image
    (runtime/images.py); a writer is called with the path and writes it atomically itself."""
    from .images import write_image

    done = []
    try:
        for path, what in outputs:
            if callable(what):
                what(path)
            else:
                write_image(path, what)
            done.append(Path(path))
    except BaseException:
        for p in done:
            p.unlink(missing_ok=True)
        raise


def write_sequence(folder, items) -> int:
    """Write the files `items` yields, (name, writer) pairs, into `folder` (created if
    missing), one at a time so that only one is in memory; if one fails, remove those written
    that were not there before (a file this call replaced stays, in its new version) and the
    folder if this call created it. Returns how many were written."""
    folder = Path(folder)
    created = not folder.exists()
    folder.mkdir(exist_ok=True)
    written, count = [], 0
    try:
        for name, writer in items:
            new = not (folder / name).exists()
            write_all([(folder / name, writer)])
            count += 1
            if new:
                written.append(folder / name)
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        if created:
            try:
                folder.rmdir()
            except OSError:
                pass
        raise
    return count


__all__ = ["RenderedView", "render_frames", "render_view", "check_output", "write_all",
           "write_sequence", "IMAGE_SUFFIXES", "ALPHA_SUFFIXES"]
