"""`nehad eval`: render a split of the dataset with a trained run and score it (SPEC section 9):
PSNR, SSIM, MS-SSIM, D-SSIM, LPIPS alex and vgg (official [-1, 1] input convention) per frame and
mean, plus render FPS (deformation + rasterization at the dataset resolution, after a warm-up).

Writes RUN/eval_SPLIT/metrics.json and the renders RUN/eval_SPLIT/r_XXX.png (atomically).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from nehad.config import config_from_dict
from nehad.data.loader import load_dataset
from nehad.trainer import RunError, cloud_at, load_run

METRIC_KEYS = ("psnr", "ssim", "ms_ssim", "d_ssim", "lpips_alex", "lpips_vgg")


def _atomic_json(path: Path, obj) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


def evaluate_run(run_dir, split: str = "test", data_dir=None, lpips: bool = True,
                 write_renders: bool = True, progress: bool = True, max_frames: int = 0) -> dict:
    from tqdm import tqdm

    from nehad.metrics import image_metrics
    from nehad.runtime.images import write_image
    from nehad.runtime.raster import render

    run = Path(run_dir)
    model, meta = load_run(run)
    cfg = config_from_dict(meta["config"])
    data = Path(data_dir) if data_dir is not None else Path(meta.get("data_dir", ""))
    if not data.is_dir():
        raise RunError(f"{run}: dataset folder {data} not found; pass --data DIR")
    background = tuple(float(v) for v in meta["background"])
    scene = load_dataset(data, splits=(split,), background=background,
                         downscale=cfg.data.downscale, frame_stride=cfg.data.frame_stride)
    frames = scene.frames[split]
    if max_frames > 0:
        frames = frames[:max_frames]
    out_dir = run / f"eval_{split}"
    out_dir.mkdir(exist_ok=True)
    degree = int(meta["sh_degree"])

    # warm-up: JIT and caches, not timed
    render(cloud_at(model, frames[0].camera.time, degree), frames[0].camera, background)
    per_frame, render_seconds = [], 0.0
    for i, frame in enumerate(tqdm(frames, desc=f"eval {split}", disable=not progress)):
        t0 = time.perf_counter()
        cloud = cloud_at(model, frame.camera.time, degree)
        rgb = render(cloud, frame.camera, background).rgb
        render_seconds += time.perf_counter() - t0
        scores = image_metrics(rgb, frame.image, require_lpips=lpips,
                               lpips_nets=("alex", "vgg") if lpips else ())
        record = {"frame": i, "file": frame.path.name, "time": frame.camera.time}
        record.update({k: scores.get(k) for k in METRIC_KEYS})
        per_frame.append(record)
        if write_renders:
            write_image(out_dir / f"r_{i:03d}.png", rgb)
    mean = {}
    for k in METRIC_KEYS:
        vals = [r[k] for r in per_frame if r[k] is not None]
        mean[k] = float(np.mean(vals)) if vals else None
    h, w = frames[0].image.shape[:2]
    result = {
        "run": str(run), "split": split, "frames": len(per_frame), "resolution": [w, h],
        "gaussians": len(model.gaussians), "mean": mean, "per_frame": per_frame,
        "fps": len(per_frame) / render_seconds if render_seconds > 0 else None,
        "fps_threads": {"torch": torch.get_num_threads(), "numba": _numba_threads()},
        "lpips_input": "[-1, 1] (official lpips convention; 3DGS/4DGS code fed [0, 1])",
    }
    _atomic_json(out_dir / "metrics.json", result)
    return result


def _numba_threads() -> int:
    import numba

    return int(numba.get_num_threads())


def format_table(result: dict) -> str:
    m = result["mean"]
    fmt = lambda v, d: "n/a" if v is None else f"{v:.{d}f}"
    lines = [f"{result['split']}: {result['frames']} frames at {result['resolution'][0]}x"
             f"{result['resolution'][1]}, {result['gaussians']} Gaussians",
             f"  PSNR {fmt(m['psnr'], 2)}  SSIM {fmt(m['ssim'], 4)}  MS-SSIM {fmt(m['ms_ssim'], 4)}"
             f"  D-SSIM {fmt(m['d_ssim'], 4)}  LPIPS-alex {fmt(m['lpips_alex'], 4)}"
             f"  LPIPS-vgg {fmt(m['lpips_vgg'], 4)}",
             f"  render {fmt(result['fps'], 1)} FPS (deformation + rasterization, "
             f"{result['fps_threads']['numba']} threads)"]
    return "\n".join(lines)
