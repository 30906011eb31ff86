"""Frames per second of `nehad render` in a warm process: deformation (onnxruntime on the exported
model, a new time every frame, so the per-time cache never hits) plus rasterization, at the
widths given (default 400 and 800: a MuJoCo scene trained at 400x400 and its 800x800 render).

    python bench/render.py MODEL [--sizes 400,800] [--frames 30] [--threads 2]

MODEL is an exported model.onnx or a training run directory (exported to a temporary file
first). The camera is the model's default camera (the dataset's first test view).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--sizes", default="400,800", help="image widths (height keeps the aspect)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    import numba

    from nehad.runtime.onnx_model import OnnxModel
    from nehad.runtime.raster import render

    tmp = None
    path = args.model
    if path.is_dir():
        from nehad.export.onnx_export import export_run

        tmp = tempfile.TemporaryDirectory()
        path = Path(tmp.name) / "model.onnx"
        export_run(args.model, path)
    numba.set_num_threads(args.threads)
    model = OnnxModel(path, threads=args.threads)
    camera = model.default_camera
    if camera is None:
        sys.exit(f"{path}: no default camera in the metadata")
    lo, hi = model.time_range
    times = np.linspace(lo, hi, args.frames + 1)
    print(f"{path.name}: {model.num_gaussians} Gaussians; threads: onnxruntime {args.threads}, "
          f"numba {numba.get_num_threads()}")
    for width in (int(w) for w in args.sizes.split(",")):
        cam = camera.with_size(width, round(width * camera.height / camera.width))
        render(model.gaussians(float(times[-1])), cam, model.background)  # warm-up
        deform_s = raster_s = 0.0
        t_all = time.perf_counter()
        for t in times[:-1]:
            t0 = time.perf_counter()
            cloud = model.gaussians(float(t))
            t1 = time.perf_counter()
            render(cloud, cam, model.background)
            t2 = time.perf_counter()
            deform_s += t1 - t0
            raster_s += t2 - t1
        total = time.perf_counter() - t_all
        n = len(times) - 1
        print(f"{cam.width}x{cam.height}: {n / total:.1f} FPS "
              f"(deformation {1e3 * deform_s / n:.1f} ms + rasterization {1e3 * raster_s / n:.1f} ms "
              f"per frame)")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
