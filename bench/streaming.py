"""Streaming measurements (issue 6, docs/streaming.md), torch-free rendering after the export.

    python bench/streaming.py layers RUN [--out RUN/streaming.json]
        RUN trained with --lod-levels L: export --split-layers RUN/layers, then per prefix of
        layers 0..K the Gaussians, the bytes a client has fetched (base.onnx + chunks), the test
        PSNR at the run's resolution and the render FPS (deformation + rasterization).

    python bench/streaming.py zoom RUN [RUN ...]
        Test PSNR at the run's resolution and zoomed out 4x (the same cameras at a quarter of the
        width and height, against the ground truth box-downsampled 4x), e.g. for a run with
        field.mipmap and one without.

Rendering is the exported ONNX model (onnxruntime) + the Numba rasterizer, with the thread
counts of NUMBA_NUM_THREADS and --threads (onnxruntime). FPS: all test views once after a
warm-up frame, deformation + rasterization, a new time every frame.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    from nehad.metrics.image import psnr_of_mse

    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return psnr_of_mse(max(mse, 1e-30))


def _box(img: np.ndarray, f: int) -> np.ndarray:
    h, w = img.shape[0] // f * f, img.shape[1] // f * f
    return img[:h, :w].reshape(h // f, f, w // f, f, -1).mean((1, 3))


def _test_frames(run: Path, split: str = "test"):
    import yaml

    from nehad.data.loader import load_dataset

    cfg = yaml.safe_load((run / "config.yaml").read_text())
    from nehad.checkpoint import load_state

    from nehad.model import RunInfo

    info = RunInfo.from_state(load_state(run / "model.pt"))
    bg = info.background
    scene = load_dataset(info.data_dir, splits=(split,), background=bg,
                         downscale=cfg["data"]["downscale"],
                         frame_stride=cfg["data"].get("frame_stride", 1))
    return scene.frames[split], bg


def _score(model_gaussians, frames, bg, zoom: int = 1) -> tuple[float, float]:
    """(mean PSNR, FPS) of rendering every frame; zoom > 1: cameras and ground truth shrunk."""
    from nehad.runtime.raster import render

    def cam_of(f):
        c = f.camera
        return c if zoom == 1 else c.with_size(c.width // zoom, c.height // zoom)

    render(model_gaussians(frames[0].camera.time), cam_of(frames[0]), bg)  # warm-up (JIT)
    psnrs, seconds = [], 0.0
    for f in frames:
        t0 = time.perf_counter()
        rgb = render(model_gaussians(f.camera.time), cam_of(f), bg).rgb
        seconds += time.perf_counter() - t0
        gt = f.image if zoom == 1 else _box(f.image, zoom)
        psnrs.append(_psnr(rgb, gt))
    return float(np.mean(psnrs)), len(frames) / seconds


def layers(args) -> None:
    from nehad.export.layers import export_split_layers
    from nehad.runtime.layers import LayeredModel

    run = args.run[0]
    folder = run / ("layers_fp16" if args.fp16_field else "layers")
    rep = export_split_layers(run, folder, fp16_field=args.fp16_field)
    frames, bg = _test_frames(run)
    man = rep.manifest
    rows = []
    for k in range(len(man["layers"])):
        model = LayeredModel(folder, threads=args.threads, max_layer=k)
        model.base.cache_size = 0
        psnr, fps = _score(model.gaussians, frames, bg)
        e = man["layers"][k]
        rows.append({"layers": f"0..{k}", "gaussians": e["cumulative_gaussians"],
                     "layer_gaussians": e["gaussians"], "layer_bytes": e["bytes"],
                     "bytes": e["cumulative_bytes"], "psnr": psnr, "fps": fps})
        print(json.dumps(rows[-1]), flush=True)
    res = {"run": str(run), "frames": len(frames),
           "resolution": [frames[0].camera.width, frames[0].camera.height],
           "field_bytes": man["field_bytes"], "bytes_per_gaussian": man["bytes_per_gaussian"],
           "train_downscales": man["train_downscales"], "threads": _threads(args), "rows": rows}
    res["fp16_field"] = bool(args.fp16_field)
    out = args.out or run / ("streaming_fp16.json" if args.fp16_field else "streaming.json")
    out.write_text(json.dumps(res, indent=1))
    total_g, total_b = rows[-1]["gaussians"], rows[-1]["bytes"]
    print(f"\n{run}: {len(frames)} test views at {res['resolution'][0]}x{res['resolution'][1]}; "
          f"field {man['field_bytes']} bytes (in base.onnx)")
    print("| layers | Gaussians | share | bytes (fetched) | share | test PSNR | FPS |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['layers']} | {r['gaussians']} | {r['gaussians'] / total_g:.0%} | "
              f"{r['bytes'] / 1e6:.2f} MB | {r['bytes'] / total_b:.0%} | {r['psnr']:.2f} | "
              f"{r['fps']:.1f} |")


def zoom(args) -> None:
    import tempfile

    from nehad.export.onnx_export import export_run
    from nehad.runtime.onnx_model import OnnxModel

    for run in args.run:
        frames, bg = _test_frames(run)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "m.onnx"
            export_run(run, path)
            model = OnnxModel(path, threads=args.threads, cache_size=0)
            full, fps = _score(model.gaussians, frames, bg)
            small, _ = _score(model.gaussians, frames, bg, zoom=4)
        import yaml

        mip = yaml.safe_load((run / "config.yaml").read_text())["field"].get("mipmap", False)
        print(json.dumps({"run": str(run), "mipmap": mip, "gaussians": model.num_gaussians,
                          "psnr_full": full, "psnr_zoom4": small, "fps": fps,
                          "threads": _threads(args)}), flush=True)


def _threads(args) -> dict:
    import numba

    return {"numba": int(numba.get_num_threads()), "onnxruntime": args.threads}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", choices=["layers", "zoom"])
    ap.add_argument("run", type=Path, nargs="+")
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--fp16-field", action="store_true",
                    help="layers: export the field's weights as float16 (nehad export "
                         "--split-layers DIR --fp16-weights)")
    args = ap.parse_args()
    {"layers": layers, "zoom": zoom}[args.what](args)


if __name__ == "__main__":
    main()
