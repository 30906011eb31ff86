"""Frames per second of `nehad render` in a warm process, split into deformation and rasterization.

Each frame is what `nehad render` and every video frame do (runtime/render.py `render_view`):
the deformation at a new time (onnxruntime on the exported model; a new time every frame, so
the per-time cache never hits), the rasterizer (projection, binning, kernels), and the rest of
the frame (the image and depth arrays render_view hands back), at the widths given (default 400 and 800: a
MuJoCo scene trained at 400x400 and its 800x800 render). The camera is the model's default
camera (the dataset's first test view).

    python bench/render.py MODEL [--sizes 400,800] [--frames 30] [--threads N] [--busy K]

MODEL is an exported model.onnx or a training run directory (exported to a temporary file
first). After the frames one after the other it times the same frames as a sequence
(runtime/render.py `render_frames`: the next frame's deformation on a second thread while this
frame is rasterized), with the model opened again with one onnxruntime thread (--threads N: N),
the rasterizer on the cores the load leaves free minus one. Threads: by default what a user
gets (numba's pool and onnxruntime's default, the rasterizer's count following the load,
runtime/threads.py); --threads N fixes both at N. Run with NUMBA_NUM_THREADS=1
OMP_NUM_THREADS=1 for the one-thread figure. --busy K starts K processes that spin on a core
each after the warm-up frame (another user's job arriving while frames are drawn) and stops
them at the end. Prints the load average before and after, and each part beside its compute
floor (bench/floors.py: the graph's multiply-adds at onnxruntime's matmul rate; the
contributing pairs at the rasterizer's inner-loop rate).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def load_average() -> str:
    try:
        return "%.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        return "n/a"


def pipelined_fps(scene, cam, times) -> float:
    """Frames per second of `render_frames` over `times` (after one warm-up sequence)."""
    from nehad.runtime.render import render_frames

    frames = [(cam, float(t)) for t in times]
    for _ in render_frames(scene, frames[:3]):
        pass
    scene.model.clear_cache()
    start = time.perf_counter()
    n = sum(1 for _ in render_frames(scene, frames))
    return n / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--sizes", default="400,800", help="image widths (height keeps the aspect)")
    ap.add_argument("--threads", type=int, default=None,
                    help="fix numba's and onnxruntime's threads (default: as a user gets them)")
    ap.add_argument("--busy", type=int, default=0,
                    help="processes spinning on a core each while the frames are timed")
    args = ap.parse_args()

    import numba

    from nehad.runtime.render import render_view
    from nehad.runtime.scene import open_scene

    tmp = None
    path = args.model
    if path.is_dir():
        from nehad.export.onnx_export import export_run

        tmp = tempfile.TemporaryDirectory()
        path = Path(tmp.name) / "model.onnx"
        export_run(args.model, path)
    scene = open_scene(path, threads=args.threads)
    fixed = {}
    if args.threads is not None:
        numba.set_num_threads(args.threads)
        fixed = {"adapt_threads": False}
    seq_scene = open_scene(path, threads=args.threads or 1)
    camera = scene.default_camera
    if camera is None:
        sys.exit(f"{path}: no default camera in the metadata")
    lo, hi = scene.time_range
    times = np.linspace(lo, hi, args.frames + 1)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from bench.raster import contributing_pairs, inner_loop_rates
    from floors import onnx_field_macs, onnx_matmul_rate

    from nehad.runtime.raster import render as raster_render

    per_row, rows = onnx_field_macs(path)
    mac_rate = onnx_matmul_rate(args.threads)
    pair_rate, _ = inner_loop_rates(5)
    deform_floor = 1e3 * per_row * rows / mac_rate
    print(f"floors: deformation {per_row} multiply-adds x {rows} Gaussians through the field "
          f"at {mac_rate / 1e9:.1f} G/s (onnxruntime float32 matmul) = {deform_floor:.2f} ms; "
          f"rasterization at {pair_rate / 1e9:.2f} G contributing pairs/s")
    print(f"{path.name}: {scene.num_gaussians} Gaussians; threads: onnxruntime "
          f"{args.threads or 'default'}, numba pool {numba.config.NUMBA_NUM_THREADS}"
          f"{'' if fixed else ' (count follows the load)'}; busy processes {args.busy}; "
          f"load average {load_average()}")
    busy = []
    try:
        for width in (int(w) for w in args.sizes.split(",")):
            cam = camera.with_size(width, round(width * camera.height / camera.width))
            render_view(scene, cam, float(times[-1]), **fixed)  # warm-up
            if args.busy and not busy:
                busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                        for _ in range(args.busy)]
                time.sleep(1.0)
            deform_s = raster_s = rest_s = 0.0
            t_all = time.perf_counter()
            for t in times[:-1]:
                t0 = time.perf_counter()
                scene.gaussians(float(t))  # the deformation; render_view then finds it cached
                t1 = time.perf_counter()
                view = render_view(scene, cam, float(t), **fixed)
                t2 = time.perf_counter()
                deform_s += t1 - t0
                raster_s += view.seconds
                rest_s += (t2 - t1) - view.seconds
            wall = time.perf_counter() - t_all
            n = len(times) - 1
            pairs = contributing_pairs(raster_render(scene.gaussians(float(times[n // 2])), cam,
                                                     adapt_threads=False))
            raster_floor = 1e3 * pairs / pair_rate
            print(f"{cam.width}x{cam.height}: {n / wall:.1f} FPS: deformation "
                  f"{1e3 * deform_s / n:.1f} ms + rasterization {1e3 * raster_s / n:.1f} ms + "
                  f"the rest {1e3 * rest_s / n:.1f} ms per frame (numba threads at the end "
                  f"{numba.get_num_threads()})", flush=True)
            print(f"{'':>9}x floor: deformation {1e3 * deform_s / n / deform_floor:.1f} "
                  f"(floor {deform_floor:.2f} ms), rasterization "
                  f"{1e3 * raster_s / n / raster_floor:.1f} (floor {raster_floor:.2f} ms, "
                  f"{pairs / 1e6:.1f} M contributing pairs)", flush=True)
            fps = pipelined_fps(seq_scene, cam, times[:-1])
            print(f"{'':>9}as a sequence (next deformation beside this rasterization, "
                  f"onnxruntime {args.threads or 1} thread(s)): {fps:.1f} FPS", flush=True)
    finally:
        for p in busy:
            p.kill()
    print(f"load average at the end: {load_average()}")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
